"""Live streams (server-sent events) over real HTTP: a session's stream from its start and
resumed with Last-Event-ID, its end when the session closes, batches applied by another
server process, heartbeats, visibility; the admin's site stream."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import httpx
import pytest

from tests.conftest import ADMIN_KEY, DEVICE_KEY, LiveServer, make_settings

SITE = {
    "name": "stream lab",
    "floors": [{"level": 0, "walls": [[-50, -50, 50, -50]]}],
    "transmitters": [{"id": "wifi:ap1", "kind": "wifi", "floor": 0, "x": 0.0, "y": 0.0}],
}


@pytest.fixture(autouse=True)
def fast_streams(live_server: LiveServer) -> Iterator[None]:
    state = live_server.app.state
    state.events_poll_s, state.events_heartbeat_s = 0.05, 0.3
    yield
    del state.events_poll_s, state.events_heartbeat_s


@pytest.fixture
def site(admin) -> int:
    answer = admin.post("/api/v1/sites", json=SITE)
    assert answer.status_code == 201, answer.text
    return answer.json()["id"]


def open_session(client: httpx.Client, site: int) -> str:
    body = {"site_id": site, "filter": "kf", "initial": {"x": 1.0, "y": 2.0, "floor": 0}}
    answer = client.post("/api/v1/sessions", json=body)
    assert answer.status_code == 201, answer.text
    return answer.json()["id"]


def feed(client: httpx.Client, sid: str, seq: int, n: int) -> None:
    steps = [{"t": seq * 10 + 0.5 * i, "length_m": 0.7, "heading_deg": 90.0} for i in range(n)]
    answer = client.post(f"/api/v1/sessions/{sid}/batches", json={"seq": seq, "steps": steps})
    assert answer.status_code == 200, answer.text


class Stream:
    """An open event stream read event by event (comments kept as ``("comment", text)``)."""

    def __init__(self, client: httpx.Client, path: str, headers: dict[str, str] | None = None):
        self._cm = client.stream("GET", path, headers=headers or {}, timeout=10)
        self.response = self._cm.__enter__()
        self._lines = self.response.iter_lines()

    def next(self, timeout: float = 10.0) -> dict:
        """The next event or comment: {"event", "id", "data"} or {"comment"}."""
        deadline = time.monotonic() + timeout
        fields: dict = {}
        for line in self._lines:
            if time.monotonic() > deadline:
                raise TimeoutError("no event in time")
            if line.startswith(":"):
                return {"comment": line[1:].strip()}
            if not line:
                if fields:
                    if "data" in fields:
                        fields["data"] = json.loads(fields["data"])
                    return fields
                continue
            name, _, value = line.partition(":")
            fields[name] = value[1:] if value.startswith(" ") else value
        raise EOFError("stream ended")

    def events(self, n: int) -> list[dict]:
        """The next ``n`` events, skipping heartbeats."""
        out: list[dict] = []
        while len(out) < n:
            item = self.next()
            if "comment" not in item:
                out.append(item)
        return out

    def close(self) -> None:
        self._cm.__exit__(None, None, None)


def test_session_stream_from_start_then_close(device, site):
    sid = open_session(device, site)
    feed(device, sid, 0, 3)
    stream = Stream(device, f"/api/v1/sessions/{sid}/events")
    try:
        assert stream.response.status_code == 200
        assert stream.response.headers["content-type"].startswith("text/event-stream")
        first = stream.events(4)
        assert [e["event"] for e in first] == ["estimate"] * 4
        assert [e["id"] for e in first] == ["0", "1", "2", "3"]
        assert [e["data"]["idx"] for e in first] == [0, 1, 2, 3]
        track = device.get(f"/api/v1/sessions/{sid}/track").json()
        assert [{k: v for k, v in e["data"].items() if k != "idx"} for e in first] == track
        feed(device, sid, 1, 2)  # new estimates arrive while the stream is open
        assert [e["data"]["idx"] for e in stream.events(2)] == [4, 5]
        assert device.delete(f"/api/v1/sessions/{sid}").status_code == 204
        closed = stream.events(1)[0]
        assert closed["event"] == "closed" and closed["data"] == {"session_id": sid, "track_length": 6}
        with pytest.raises(EOFError):
            stream.next()
    finally:
        stream.close()


def test_session_stream_resumes_after_last_event_id(device, site):
    sid = open_session(device, site)
    feed(device, sid, 0, 5)  # indexes 0..5
    stream = Stream(device, f"/api/v1/sessions/{sid}/events", {"Last-Event-ID": "3"})
    try:
        assert [e["id"] for e in stream.events(2)] == ["4", "5"]
        device.delete(f"/api/v1/sessions/{sid}")
        assert stream.events(1)[0]["event"] == "closed"
    finally:
        stream.close()
    # a closed session's stream replays the rest and ends at once
    stream = Stream(device, f"/api/v1/sessions/{sid}/events", {"Last-Event-ID": "4"})
    try:
        assert [e.get("id") for e in stream.events(2)] == ["5", None]
    finally:
        stream.close()
    assert device.get(f"/api/v1/sessions/{sid}/events", headers={"Last-Event-ID": "x"}).status_code == 422


def test_session_stream_sees_batches_of_another_server_process(device, site, database_url):
    """Two servers on one database (as replicas): the stream is read from one while the
    batches go to the other."""
    other = LiveServer(make_settings(database_url, embedded_worker=False)).start()
    try:
        with httpx.Client(base_url=other.url, headers={"Authorization": f"Bearer {DEVICE_KEY}"}, timeout=60) as there:
            sid = open_session(there, site)
            stream = Stream(device, f"/api/v1/sessions/{sid}/events")
            try:
                assert [e["id"] for e in stream.events(1)] == ["0"]
                feed(there, sid, 0, 2)
                got = stream.events(2)
                assert [e["id"] for e in got] == ["1", "2"]
                assert got[-1]["data"]["x"] == pytest.approx(1.0 + 2 * 0.7)
                assert there.delete(f"/api/v1/sessions/{sid}").status_code == 204
                assert stream.events(1)[0]["event"] == "closed"
            finally:
                stream.close()
    finally:
        other.stop()


def test_heartbeat_comment(device, site):
    sid = open_session(device, site)
    stream = Stream(device, f"/api/v1/sessions/{sid}/events")
    try:
        assert stream.events(1)[0]["id"] == "0"
        assert stream.next(timeout=5) == {"comment": "heartbeat"}
    finally:
        stream.close()


def test_session_stream_visibility(device, admin, anonymous, site):
    theirs = open_session(admin, site)  # opened with the admin key: not the device's
    assert device.get(f"/api/v1/sessions/{theirs}/events").status_code == 404
    assert device.get("/api/v1/sessions/nope/events").status_code == 404
    assert anonymous.get(f"/api/v1/sessions/{theirs}/events").status_code == 401
    mine = open_session(device, site)
    admin.delete(f"/api/v1/sessions/{mine}")
    stream = Stream(admin, f"/api/v1/sessions/{mine}/events")  # an admin key sees every session
    try:
        assert [e["event"] for e in stream.events(2)] == ["estimate", "closed"]
    finally:
        stream.close()


def test_site_stream(admin, device, site):
    assert device.get(f"/api/v1/sites/{site}/events").status_code == 403
    assert admin.get("/api/v1/sites/999999/events").status_code == 404
    a = open_session(device, site)
    feed(device, a, 0, 3)  # a's track: 0..3; the stream starts at its latest estimate
    stream = Stream(admin, f"/api/v1/sites/{site}/events")
    try:
        first = stream.events(1)[0]
        assert first["event"] == "estimate" and first["data"]["session_id"] == a and first["data"]["idx"] == 3
        assert "id" not in first
        b = open_session(device, site)  # opened later: sent from its first estimate
        got = stream.events(1)[0]["data"]
        assert (got["session_id"], got["idx"]) == (b, 0)
        feed(device, a, 1, 1)
        got = stream.events(1)[0]["data"]
        assert (got["session_id"], got["idx"]) == (a, 4)
        feed(device, b, 0, 1)
        device.delete(f"/api/v1/sessions/{b}")
        got = stream.events(2)
        assert (got[0]["data"]["session_id"], got[0]["data"]["idx"]) == (b, 1)  # its last estimate is not lost
        assert got[1] == {"event": "closed", "data": {"session_id": b}}
    finally:
        stream.close()


def test_streams_in_openapi(admin):
    paths = admin.get("/openapi.json").json()["paths"]
    assert "text/event-stream" in paths["/api/v1/sessions/{session_id}/events"]["get"]["responses"]["200"]["content"]
    assert "/api/v1/sites/{site_id}/events" in paths
    assert ADMIN_KEY  # the keys the fixtures use


def test_schema_states_the_conventions(anonymous):
    """The contract's conventions in the OpenAPI schema (docs/api-conventions.md): `filter` and
    `algorithm` are enums built from the registries; units and frame are in the descriptions."""
    from server.estimation.fingerprint.registry import ALGORITHMS
    from server.estimation.tracking import tracker_names

    schemas = anonymous.get("/openapi.json").json()["components"]["schemas"]
    assert schemas["SessionIn"]["properties"]["filter"]["enum"] == list(tracker_names())
    assert schemas["ModelIn"]["properties"]["algorithm"]["enum"] == sorted(ALGORITHMS)
    assert "clockwise from the site's +y" in schemas["StepIn"]["properties"]["heading_deg"]["description"]
    assert "m²" in schemas["EstimateOut"]["properties"]["covariance"]["description"]
    assert "seconds" in schemas["ScanIn"]["properties"]["t"]["description"]
    assert "east" in schemas["FingerprintIn"]["properties"]["x"]["description"]
