"""GET /sessions/{id}/track?since=&limit= (extension): pages walk the whole track once, in
order; a Link rel="next" header only while more remains; bounds; smoothed does not combine;
another device's session stays 404; without the parameters the answer is the whole list."""

from __future__ import annotations

import re

import httpx
import pytest

from tests.api.test_sessions import batch, open_session, positioning, site  # noqa: F401  (fixtures)

_LINK = re.compile(r'^<(?P<url>[^>]+)>; rel="next"$')


def _track_session(device, site, batches: int = 5) -> str:  # noqa: F811
    sid = open_session(device, site, "kf")["id"]
    for seq in range(batches):
        answer = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(seq, 2.0 * seq, 4))
        assert answer.status_code == 200, answer.text
    return sid


@pytest.mark.parametrize("limit", [1, 3, 7, 21, 10_000])
def test_paging_walks_the_whole_track_once_in_order(device, site, limit):  # noqa: F811
    sid = _track_session(device, site)
    whole = device.get(f"/api/v1/sessions/{sid}/track")
    assert whole.status_code == 200 and "link" not in whole.headers
    full = whole.json()
    assert len(full) == 21  # init + 5 batches of 4 steps

    got: list[dict] = []
    url: str | None = f"/api/v1/sessions/{sid}/track?limit={limit}"
    pages = 0
    while url is not None:
        answer = device.get(url)
        assert answer.status_code == 200, answer.text
        page = answer.json()
        assert isinstance(page, list) and 1 <= len(page) <= limit
        got.extend(page)
        pages += 1
        link = answer.headers.get("link")
        if link is None:
            url = None
        else:
            m = _LINK.match(link)
            assert m, link
            assert len(page) == limit  # only a full page may be followed by more
            url = m.group("url")
            assert f"since={len(got) - 1}" in url and f"limit={limit}" in url
    assert got == full
    assert pages == -(-len(full) // limit)


def test_since_alone_and_past_the_end(device, site):  # noqa: F811
    sid = _track_session(device, site, 2)
    full = device.get(f"/api/v1/sessions/{sid}/track").json()
    rest = device.get(f"/api/v1/sessions/{sid}/track", params={"since": 4})
    assert rest.json() == full[5:] and "link" not in rest.headers
    assert device.get(f"/api/v1/sessions/{sid}/track", params={"since": -1}).json() == full
    end = device.get(f"/api/v1/sessions/{sid}/track", params={"since": len(full) - 1, "limit": 5})
    assert end.status_code == 200 and end.json() == [] and "link" not in end.headers
    # a page cut exactly at the end has no next link
    exact = device.get(f"/api/v1/sessions/{sid}/track", params={"since": len(full) - 4, "limit": 3})
    assert exact.json() == full[-3:] and "link" not in exact.headers


def test_a_page_boundary_while_batches_arrive(device, site):  # noqa: F811
    sid = _track_session(device, site, 1)
    first = device.get(f"/api/v1/sessions/{sid}/track", params={"limit": 5})
    assert len(first.json()) == 5 and "link" not in first.headers
    assert device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 2.0, 4)).status_code == 200
    more = device.get(f"/api/v1/sessions/{sid}/track", params={"since": 4, "limit": 5})
    assert first.json() + more.json() == device.get(f"/api/v1/sessions/{sid}/track").json()


@pytest.mark.parametrize("params", [{"limit": 0}, {"limit": 10_001}, {"since": -2}, {"limit": "x"},
                                    {"since": 2**31}])
def test_bounds_are_422(device, site, params):  # noqa: F811
    sid = _track_session(device, site, 1)
    assert device.get(f"/api/v1/sessions/{sid}/track", params=params).status_code == 422


def test_smoothed_does_not_combine_with_paging(device, site):  # noqa: F811
    sid = _track_session(device, site, 1)
    for params in ({"smoothed": "true", "limit": 2}, {"smoothed": "true", "since": 0}):
        answer = device.get(f"/api/v1/sessions/{sid}/track", params=params)
        assert answer.status_code == 422 and "smoothed" in answer.text
    assert device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "false", "limit": 2}).status_code == 200


def test_another_devices_session_stays_404(live_server, device, admin, site):  # noqa: F811
    from server.auth import create_key
    from server.db import Database

    db = Database(live_server.app.state.settings.database_url)
    _, other_key = create_key(db, "phone 2", "device")
    db.dispose()
    sid = _track_session(device, site, 1)
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {other_key}"}) as other:
        for params in ({"limit": 2}, {"since": 0}, {"since": 0, "limit": 2}):
            assert other.get(f"/api/v1/sessions/{sid}/track", params=params).status_code == 404
            assert other.get("/api/v1/sessions/nope/track", params=params).status_code == 404
    assert len(admin.get(f"/api/v1/sessions/{sid}/track", params={"limit": 2}).json()) == 2


def test_refused_fix_marks_on_pages_of_many_batches(device, site, positioning):  # noqa: F811
    """A page reads the answers of its own batches only; the marks must still be the whole track's."""
    sid = open_session(device, site, "kf")["id"]
    far = [{"t": 0.0, "rss": {"wifi:ap3": -40}}]  # a fix at (0, 10): far from the walk along y = 2
    for seq in range(8):
        body = batch(seq, 2.0 * seq, 2, [{**far[0], "t": 2.0 * seq + 0.75}] if seq in (3, 5) else None)
        assert device.post(f"/api/v1/sessions/{sid}/batches", json=body).status_code == 200
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    marked = [i for i, e in enumerate(track) if "fix_refused" in e]
    assert marked, track
    for limit in (1, 2, 3, 5):
        got: list[dict] = []
        while True:
            answer = device.get(f"/api/v1/sessions/{sid}/track", params={"since": len(got) - 1, "limit": limit})
            got.extend(answer.json())
            if "link" not in answer.headers:
                break
        assert got == track, limit


@pytest.mark.parametrize("marks", [None, (False, False), (True, False), (False, True), (True, True)])
@pytest.mark.parametrize("t", [None, 12.5])
def test_page_items_are_the_schema_dump(marks, t):
    """Pages build their items as plain dicts (the cost of 1,000 pydantic models): each equals
    the documented schema's dump, with ``fix_refused`` and ``snap_refused`` each only when true."""
    from server.api.sessions import track_estimate_json, track_estimate_out
    from server.domain import GateMarks
    from server.estimation.types import Estimate

    e = Estimate(t, 1.5, -2.25, 3, ((1.0, 0.1), (0.1, 2.0)), "scan", 2)
    m = None if marks is None else GateMarks(*marks)
    got = track_estimate_json(e, m)
    assert got == track_estimate_out(e, m).model_dump(mode="json", exclude_unset=True)
    assert ("fix_refused" in got, "snap_refused" in got) == (marks or (False, False))


def test_live_streams_carry_the_refused_fix_marks(device, admin, site, positioning, live_server):  # noqa: F811
    """The session's and the site's event streams mark the same estimates as the stored track."""
    from tests.api.test_events import Stream

    state = live_server.app.state
    state.events_poll_s = 0.05
    sid = open_session(device, site, "kf")["id"]
    site_stream = Stream(admin, f"/api/v1/sites/{site}/events")
    try:
        far = {"t": 0.0, "rss": {"wifi:ap3": -40}}  # a fix at (0, 10): far from the walk along y = 2
        for seq in range(6):
            body = batch(seq, 2.0 * seq, 2, [{**far, "t": 2.0 * seq + 0.75}] if seq in (2, 4) else None)
            assert device.post(f"/api/v1/sessions/{sid}/batches", json=body).status_code == 200
        track = device.get(f"/api/v1/sessions/{sid}/track").json()
        assert any("fix_refused" in e for e in track)
        stream = Stream(device, f"/api/v1/sessions/{sid}/events")
        try:
            got = [e["data"] for e in stream.events(len(track))]
        finally:
            stream.close()
        assert [{k: v for k, v in d.items() if k != "idx"} for d in got] == track
        seen: dict[int, dict] = {}
        while len(seen) < len(track) - 1 or max(seen, default=-1) < len(track) - 1:
            d = site_stream.events(1)[0]["data"]
            if d["session_id"] == sid:
                seen[d["idx"]] = {k: v for k, v in d.items() if k not in ("idx", "session_id")}
        # (the initial estimate was sent before the first batch gave it its time)
        assert {i: d for i, d in seen.items() if i > 0 and d != track[i]} == {}, track
        assert [i for i in seen if "fix_refused" in seen[i]] == [i for i, e in enumerate(track) if "fix_refused" in e]
    finally:
        site_stream.close()
        del state.events_poll_s


@pytest.mark.parametrize("with_estimate", [False, True])
@pytest.mark.parametrize("microsecond", [0, 123456])
def test_session_list_items_are_the_schema_dump(with_estimate, microsecond):
    """Session lists are built as plain dicts and encoded by orjson: each item equals the
    documented schema's JSON, the time included."""
    import json
    from datetime import UTC, datetime

    import orjson

    from server.api.sessions import session_json, session_out
    from server.domain import SessionInfo
    from server.estimation.types import Estimate

    e = Estimate(3.5, 1.5, -2.25, 1, ((1.0, 0.1), (0.1, 2.0)), "step", 2) if with_estimate else None
    info = SessionInfo(id="abc", site_id=7, owner_key="k", filter="pf", model_id=None, status="open", estimate=e,
                       created_at=datetime(2026, 12, 1, 15, 4, 5, microsecond, tzinfo=UTC), last_seq=4,
                       track_length=9)
    got = json.loads(orjson.dumps(session_json(info), option=orjson.OPT_UTC_Z))
    # (as the single-session routes answer it: unset fields left out, filter_params for one)
    assert got == json.loads(session_out(info).model_dump_json(exclude_unset=True))
