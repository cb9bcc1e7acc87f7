"""Tracking sessions, batch answers, tracks and crowd points on a real database."""

from __future__ import annotations

from dataclasses import replace

import pytest

from server.domain import BatchAnswer, GateMarks
from server.estimation.types import CrowdPoint, Estimate, ScanNote
from server.store import sessions

START = Estimate(None, 1.0, 2.0, 0, ((1.0, 0.0), (0.0, 1.0)), "init")


def step(t: float, x: float) -> Estimate:
    return Estimate(t, x, 2.0, 0, ((0.5, 0.1), (0.1, 0.5)), "step")


@pytest.fixture
def session_id(db, site_id) -> str:
    with db.transaction() as s:
        info = sessions.add_session(s, "s-1", site_id, "owner-hash", "ekf", None, {"estimate": START.to_dict()}, [START])
    assert (info.status, info.last_seq, info.track_length, info.estimate) == ("open", -1, 1, START)
    return info.id


def test_a_session_round_trips_and_lists_by_owner_site_and_status(db, site_id, session_id):
    with db.transaction() as s:
        sessions.add_session(s, "s-2", site_id, "other-hash", "pf", None, {}, [])
    with db.transaction() as s:
        got = sessions.get_session(s, session_id)
        assert got is not None
        assert (got.site_id, got.owner_key, got.filter, got.estimate) == (site_id, "owner-hash", "ekf", START)
        assert [i.id for i in sessions.list_sessions(s, "owner-hash", None, None, 10)] == ["s-1"]
        assert {i.id for i in sessions.list_sessions(s, None, site_id, "open", 10)} == {"s-1", "s-2"}
        assert sessions.list_sessions(s, None, site_id + 1, None, 10) == []
        assert sessions.get_session(s, "nope") is None
        assert sessions.close_session(s, "s-2") and not sessions.close_session(s, "s-2")
        assert [i.id for i in sessions.list_sessions(s, None, None, "closed", 10)] == ["s-2"]


def test_a_batch_is_stored_once_with_its_answer_and_estimates(db, session_id):
    answer = BatchAnswer(0, step(1.5, 2.0), 2, 0, (ScanNote(0, "no model"),), ())
    with db.write() as conn:
        assert sessions.save_batch(conn, session_id, expected_last_seq=-1, state={"v": 1}, answer=answer,
                                   first_idx=1, estimates=[step(1.0, 1.5), step(1.5, 2.0)], init_t=1.0)
    with db.write() as conn:  # a second writer that read the same version loses and writes nothing
        assert not sessions.save_batch(conn, session_id, expected_last_seq=-1, state={"v": 2}, answer=answer,
                                       first_idx=1, estimates=[step(9.0, 9.0)])
    with db.read() as conn:
        state = sessions.feed_state(conn, session_id)
        assert state is not None and (state.last_seq, state.track_length, state.state) == (0, 3, {"v": 1})
        assert sessions.batch_answer(conn, session_id, 0) == answer
        assert sessions.batch_answer(conn, session_id, 1) is None
    with db.transaction() as s:
        track = sessions.track(s, session_id)
    # the initial estimate took the time of the batch's first input
    assert track == [replace(START, t=1.0), step(1.0, 1.5), step(1.5, 2.0)]


def test_a_closed_session_takes_no_batch(db, session_id):
    with db.transaction() as s:
        sessions.close_session(s, session_id)
    with db.write() as conn:
        assert not sessions.save_batch(conn, session_id, expected_last_seq=-1, state={},
                                       answer=BatchAnswer(0, None, 0, 0), first_idx=1, estimates=[])


def test_an_answer_stored_before_the_gate_reads_back_without_rejected_fixes():
    stored = {"seq": 3, "estimate": None, "applied_steps": 0, "applied_scans": 1,
              "skipped_scans": [{"index": 0, "reason": "why"}]}
    assert BatchAnswer.from_dict(stored) == BatchAnswer(3, None, 0, 1, (ScanNote(0, "why"),), ())


def test_an_answer_with_refused_snaps_reads_back_as_stored():
    answer = BatchAnswer(4, None, 0, 2, (), (ScanNote(0, "fix"),), (ScanNote(1, "snap"),))
    assert BatchAnswer.from_dict(answer.to_dict()) == answer


def test_gate_marks_land_on_the_scan_estimates_of_the_refusing_batches(db, session_id):
    """A batch of 4 scans, scan 1 skipped (it left no estimate): the fix refused at scan 2 and
    the snaps refused at scans 2 and 3 mark the second and third scan estimates; a later batch
    without refusals marks nothing, and a seq range reads only its own batches."""
    def scan(t: float) -> Estimate:
        return replace(step(t, t), source="scan")

    first = BatchAnswer(0, scan(4.0), 1, 3, (ScanNote(1, "no fix"),), (ScanNote(2, "fix"),),
                        (ScanNote(2, "snap"), ScanNote(3, "snap")))
    estimates = [scan(1.0), step(1.5, 1.5), scan(3.0), scan(4.0)]  # track indexes 1..4
    with db.write() as conn:
        assert sessions.save_batch(conn, session_id, expected_last_seq=-1, state={}, answer=first,
                                   first_idx=1, estimates=estimates)
        assert sessions.save_batch(conn, session_id, expected_last_seq=0, state={},
                                   answer=BatchAnswer(1, scan(5.0), 0, 1), first_idx=5, estimates=[scan(5.0)])
    with db.transaction() as s:
        assert sessions.gate_marks(s, session_id) == {3: GateMarks(True, True), 4: GateMarks(snap_refused=True)}
        assert sessions.gate_marks(s, session_id, (1, 1)) == {}


def test_crowd_points_are_found_in_their_box_on_their_floor_and_updated(db, site_id):
    with db.write() as conn:
        sessions.add_crowd_fingerprint(conn, site_id, CrowdPoint(1.0, 1.0, 0, {"wifi:a": -60.0}, 2), 370.0, 5.0)
        sessions.add_crowd_fingerprint(conn, site_id, CrowdPoint(1.2, 1.0, 1, {"wifi:a": -70.0}), None, None)
    with db.write() as conn:
        near = sessions.nearby_crowd_points(conn, site_id, 0, 1.5, 1.5, 1.0)
        assert [p for _, p in near] == [CrowdPoint(1.0, 1.0, 0, {"wifi:a": -60.0}, 2)]
        assert sessions.nearby_crowd_points(conn, site_id, 0, 5.0, 5.0, 1.0) == []
        sessions.update_crowd_fingerprint(conn, near[0][0], CrowdPoint(1.1, 1.1, 0, {"wifi:a": -62.0}, 3))
    with db.write() as conn:
        assert [p for _, p in sessions.nearby_crowd_points(conn, site_id, 0, 1.0, 1.0, 1.0)] == [
            CrowdPoint(1.1, 1.1, 0, {"wifi:a": -62.0}, 3)
        ]
