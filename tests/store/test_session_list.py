"""A session list reads ``last_seq``, ``track_length`` and the estimate without the tracker state:
each listed session must still equal the session read alone."""

from __future__ import annotations

from server.domain import BatchAnswer
from server.estimation.types import Estimate
from server.store import sessions

COV = ((0.5, 0.1), (0.1, 0.5))


def est(t: float | None, x: float, source: str = "step") -> Estimate:
    return Estimate(t, x, 2.0, 0, COV, source)


def feed(db, session_id: str, last_seq: int, seq: int, first_idx: int, estimates: list[Estimate],
         current: Estimate | None) -> None:
    """One applied batch, its state holding the session's current estimate (as the service stores it)."""
    state = {} if current is None else {"estimate": current.to_dict()}
    answer = BatchAnswer(seq, current, len(estimates), 0, (), ())
    with db.write() as conn:
        assert sessions.save_batch(conn, session_id, expected_last_seq=last_seq, state=state, answer=answer,
                                   first_idx=first_idx, estimates=estimates)


def test_each_listed_session_equals_the_session_read_alone(db, site_id):
    start = est(None, 1.0, "init")
    with db.transaction() as s:
        sessions.add_session(s, "no-track", site_id, "owner", "pf", None, {}, [])
        sessions.add_session(s, "started", site_id, "owner", "pf", None, {"estimate": start.to_dict()}, [start])
        sessions.add_session(s, "walked", site_id, "owner", "pf", None, {"estimate": start.to_dict()}, [start])
        sessions.add_session(s, "unstarted-walk", site_id, "owner", "ekf", None, {}, [])
        sessions.add_session(s, "closed", site_id, "owner", "kf", None, {"estimate": start.to_dict()}, [start])
        sessions.add_session(s, "someone-else", site_id, "other", "pf", None, {}, [])
    walk = [est(1.0, 1.5), est(1.5, 2.0), est(4.0, 3.0)]
    feed(db, "walked", -1, 0, 1, walk[:2], walk[1])
    feed(db, "walked", 0, 1, 3, [], walk[1])  # a batch that added no estimate
    feed(db, "walked", 1, 5, 3, walk[2:], walk[2])  # seqs may jump
    feed(db, "unstarted-walk", -1, 0, 0, walk[:1], walk[0])
    feed(db, "closed", -1, 2, 1, walk[:1], walk[0])
    with db.transaction() as s:
        assert sessions.close_session(s, "closed")
    with db.transaction() as s:
        listed = {i.id: i for i in sessions.list_sessions(s, "owner", None, None, 100)}
        alone = {sid: sessions.get_session(s, sid) for sid in listed}
        every = sessions.list_sessions(s, None, site_id, None, 100)
    assert set(listed) == {"no-track", "started", "walked", "unstarted-walk", "closed"}
    assert listed == alone
    assert (listed["walked"].last_seq, listed["walked"].track_length, listed["walked"].estimate) == (5, 4, walk[2])
    assert (listed["no-track"].last_seq, listed["no-track"].track_length, listed["no-track"].estimate) == (-1, 0, None)
    assert (listed["unstarted-walk"].last_seq, listed["unstarted-walk"].track_length) == (0, 1)
    assert {i.id for i in every} == {*listed, "someone-else"} and all(i == alone.get(i.id, i) for i in every)


def test_a_site_poll_reads_each_open_session_s_track_length(db, site_id):
    start = est(None, 1.0, "init")
    with db.transaction() as s:
        sessions.add_session(s, "none", site_id, "owner", "pf", None, {}, [])
        sessions.add_session(s, "walked", site_id, "owner", "pf", None, {}, [start])
        sessions.add_session(s, "closed", site_id, "owner", "pf", None, {}, [start])
    feed(db, "walked", -1, 0, 1, [est(1.0, 1.5), est(1.5, 2.0)], est(1.5, 2.0))
    with db.transaction() as s:
        assert sessions.close_session(s, "closed")
    with db.transaction() as s:
        polled = sessions.open_sessions_of_site(s, site_id)
        assert polled == {sid: sessions.get_session(s, sid).track_length for sid in ("none", "walked")}
    assert polled == {"none": 0, "walked": 3}
