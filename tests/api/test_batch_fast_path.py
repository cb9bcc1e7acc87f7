"""BatchFastPath answers a batch that goes well with the route's bytes and stores what the route
stores, and leaves every other request to the route: each refusal and error is the route's own,
word for word, and nothing it refuses is stored."""

from __future__ import annotations

import json
import math
import time

import httpx
import pytest

import server.api.sessions as sessions_module
from server.api.deps import session_service
from server.auth import create_key
from tests.api.test_locate_fast_path import Chunked
from tests.api.test_sessions import BAD_BATCHES, batch, open_session, site, steps  # noqa: F401  (site: the fixture)
from tests.conftest import ADMIN_KEY
from tests.helpers.calls import count_async_calls, failures_since


@pytest.fixture
def route_calls(monkeypatch) -> list[int]:
    """How many requests the route itself answered (only the route parses through ``read_json``)."""
    return count_async_calls(monkeypatch, sessions_module, "read_json")


@pytest.fixture
def two_ways(live_server):
    """``ask(client, path_of, **kw)`` → the answers to the same request sent to two sessions that
    were opened and fed alike, one with the fast path on, the other with it off."""
    state = live_server.app.state

    def ask(client: httpx.Client, where: tuple[str, str], method: str = "POST", **kw) -> tuple[httpx.Response, ...]:
        try:
            state.batch_fast_path = True
            fast = client.request(method, where[0], **kw)
            state.batch_fast_path = False
            route = client.request(method, where[1], **kw)
        finally:
            state.batch_fast_path = True
        return fast, _as_if(route, _session_id(where[1]), _session_id(where[0]))

    yield ask
    state.batch_fast_path = True


def _session_id(url: str) -> str:
    return url.split("/")[4]


def _as_if(answer: httpx.Response, session_id: str, other: str) -> httpx.Response:
    """``answer`` as if it were about session ``other`` (errors name the session; the ids are alike long)."""
    if session_id == other:
        return answer
    content = answer.content.replace(session_id.encode(), other.encode())
    return httpx.Response(answer.status_code, headers=answer.headers, content=content)


def _same(fast: httpx.Response, route: httpx.Response) -> None:
    assert fast.status_code == route.status_code, (fast.text, route.text)
    assert fast.content == route.content, (fast.text, route.text)
    for name in ("content-type", "content-length", "www-authenticate", "retry-after"):
        assert fast.headers.get(name) == route.headers.get(name), name


def _pair(client: httpx.Client, site: int, filter: str = "kf", initial: bool = True) -> tuple[str, str]:  # noqa: F811
    """Two sessions opened alike: their batch URLs."""
    return tuple(f"/api/v1/sessions/{open_session(client, site, filter, initial)['id']}/batches"  # type: ignore[return-value]
                 for _ in range(2))


def _stored_alike(client: httpx.Client, urls: tuple[str, str]) -> None:
    """The two sessions' stored state and track are the same (but for their ids and times)."""
    infos, tracks = [], []
    for url in urls:
        base = url.removesuffix("/batches")
        info = client.get(base).json()
        infos.append({k: v for k, v in info.items() if k not in ("id", "created_at")})
        tracks.append(client.get(f"{base}/track").content)
    assert infos[0] == infos[1]
    assert tracks[0] == tracks[1]


def _scan(t: float, x: float) -> dict:
    """A scan heard as if at (x, 0) by the lab's transmitters (default R0/γ)."""
    return {"t": t, "rss": {"wifi:ap1": -45.0 - 25 * math.log10(max(x, 0.5)),
                            "wifi:ap2": -45.0 - 25 * math.log10(max(abs(10 - x), 0.5)),
                            "wifi:ap3": -45.0 - 25 * math.log10(math.hypot(x, 10))}}


@pytest.mark.parametrize("filter", ["kf", "ekf"])  # (a particle filter draws its own particles per session)
def test_the_fast_path_answers_and_stores_as_the_route_does(device, site, two_ways, route_calls, filter):  # noqa: F811
    urls = _pair(device, site, filter, initial=filter != "ekf")
    bodies = [
        batch(0, 0.0, 3),
        {"seq": 1, "steps": steps(2.0, 2), "scans": [_scan(2.2, 3.0), _scan(2.7, 3.5)]},
        {"seq": 2, "scans": [_scan(4.0, 4.0), {"t": 4.1, "rss": {"wifi:nowhere": -60.0}}]},
        {"seq": 3},
        {"seq": 5, "steps": [{**s, "length_std_m": 0.1, "heading_std_deg": 3.0} for s in steps(5.0, 3)]},
    ]
    for body in bodies:
        before = len(route_calls)
        fast, route = two_ways(device, urls, json=body)
        assert fast.status_code == 200, fast.text
        _same(fast, route)
        assert len(route_calls) == before + 1  # the second, fast path off; the first never reached the route
    for body in bodies[1:3]:  # replays: the stored answer
        _same(*two_ways(device, urls, json=body))
    _stored_alike(device, urls)


def test_an_admin_key_and_a_stored_device_key_are_served(device, site, live_server, two_ways, route_calls):  # noqa: F811
    _, key = create_key(live_server.app.state.db, "phone", "device")
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {key}"}) as stored, \
            httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {ADMIN_KEY}"}) as admin_key:
        urls = _pair(stored, site)
        fast, route = two_ways(stored, urls, json=batch(0, 0.0, 2))
        assert fast.status_code == 200
        _same(fast, route)
        _same(*two_ways(admin_key, urls, json=batch(1, 1.0, 2)))  # an admin key may feed any session
        _same(*two_ways(device, urls, json=batch(2, 2.0, 2)))  # another device key: 404
        assert len(route_calls) == 3 + 1
        _stored_alike(stored, urls)


def test_every_refusal_and_error_is_the_routes_and_stores_nothing(device, anonymous, site, two_ways, snapshot):  # noqa: F811
    urls = _pair(device, site)
    _same(*two_ways(device, urls, json=batch(0, 0.0, 2)))  # last t 0.5
    good = batch(1, 1.0, 2)
    raw = json.dumps(good).encode()
    cases = [
        (anonymous, {"json": good}),  # 401: no key
        (anonymous, {"json": good, "headers": {"Authorization": "Basic abc"}}),
        (anonymous, {"json": good, "headers": {"Authorization": "Bearer"}}),
        (anonymous, {"json": good, "headers": {"Authorization": "Bearer not-a-key"}}),
        (device, {"content": raw, "headers": {"Content-Type": "text/plain"}}),  # 415
        (device, {"content": b"{not json", "headers": {"Content-Type": "application/json"}}),  # 422
        (device, {"json": {}}),
        (device, {"json": {**good, "extra": 1}}),
        (device, {"json": batch(1, 0.0, 2)}),  # 422: before the last applied time
        (device, {"json": batch(0, 9.0, 2)}),  # 200: a replay, not applied again (the stored answer)
        (device, {"json": {"seq": 1, "steps": steps(1.0, 1001)}}),  # 413
        (device, {"json": {"seq": 1, "scans": [_scan(1.0, 2.0)] * 1001}}),
        (device, {"content": Chunked([raw[:10], raw[10:]])}),  # no declared length: the route, 200 then
        *[(device, {"content": json.dumps(body).encode(), "headers": {"Content-Type": "application/json"}})
          for body, _ in BAD_BATCHES],
    ]
    for client, kw in cases:
        before = snapshot()
        fast, route = two_ways(client, urls, **kw)
        _same(fast, route)
        if fast.status_code != 200:
            assert snapshot() == before, kw
    _stored_alike(device, urls)
    for where in [("/api/v1/sessions/nope/batches",) * 2, (urls[0] + "/", urls[1] + "/")]:
        _same(*two_ways(device, where, json=batch(2, 5.0)))
    _same(*two_ways(device, urls, method="GET"))  # 405
    closed = [url.removesuffix("/batches") for url in urls]
    for url in closed:
        assert device.delete(url).status_code == 204
    before = snapshot()
    fast, route = two_ways(device, urls, json=batch(3, 9.0))  # 409: closed
    assert fast.status_code == 409
    _same(fast, route)
    assert snapshot() == before


def test_a_wrong_key_is_counted_once(device, site, live_server):  # noqa: F811
    url = _pair(device, site)[0]
    failures = live_server.app.state.auth.failures
    since = time.monotonic()
    with httpx.Client(base_url=live_server.url, headers={"Authorization": "Bearer lk_wrong"}) as wrong:
        assert wrong.post(url, json=batch(0, 0.0)).status_code == 401
    assert failures_since(failures, since) == 1


def test_dependency_overrides_send_every_request_to_the_route(device, site, live_server, route_calls):  # noqa: F811
    url = _pair(device, site)[0]
    app = live_server.app
    app.dependency_overrides[session_service] = lambda: app.state.sessions
    try:
        assert device.post(url, json=batch(0, 0.0)).status_code == 200
    finally:
        app.dependency_overrides.pop(session_service)
    assert len(route_calls) == 1
