"""LocateFastPath answers a locate that goes well with the route's bytes, and leaves every other
request to the route: each refusal and error is the route's own, word for word."""

from __future__ import annotations

import time
from collections.abc import Iterator

import httpx
import numpy as np
import pytest

import server.api.locate as locate_module
from server.api.deps import positioning_service
from server.auth import create_key
from tests.api.test_models import SYNTH, site, train  # noqa: F401  (site: the fixture)
from tests.conftest import ADMIN_KEY
from tests.helpers.calls import count_async_calls, failures_since


@pytest.fixture
def route_calls(monkeypatch) -> list[int]:
    """How many requests the route itself answered (it runs its work through ``run_blocking``)."""
    return count_async_calls(monkeypatch, locate_module, "run_blocking")


@pytest.fixture
def both_ways(live_server) -> Iterator:
    """``ask(request)`` → (fast path on, fast path off) answers to the same request."""
    state = live_server.app.state

    def ask(client: httpx.Client, method: str, url: str, **kw) -> tuple[httpx.Response, httpx.Response]:
        try:
            state.locate_fast_path = True
            fast = client.request(method, url, **kw)
            state.locate_fast_path = False
            route = client.request(method, url, **kw)
        finally:
            state.locate_fast_path = True
        return fast, route

    yield ask
    state.locate_fast_path = True


def _same(fast: httpx.Response, route: httpx.Response) -> None:
    assert fast.status_code == route.status_code, (fast.text, route.text)
    assert fast.content == route.content
    for name in ("content-type", "content-length", "www-authenticate", "retry-after"):
        assert fast.headers.get(name) == route.headers.get(name), name


class Chunked:
    """A body sent in chunks (no Content-Length), the same each time it is sent."""

    def __init__(self, parts: list[bytes]):
        self.parts = parts

    def __iter__(self):
        return iter(self.parts)


def _scans(n: int) -> list[dict]:
    rng = np.random.default_rng(4)
    out = []
    for i, (_, x, y, f) in enumerate(SYNTH.rp[:n]):
        scan = SYNTH.scan(x, y, f, None, rng, 1.0)
        out.append({"rss": scan} if i % 3 else {"rss": {t: v + 6.0 for t, v in scan.items()}, "heading_deg": 90.0})
    return out


@pytest.mark.parametrize("algorithm", ["wknn", "knn"])
def test_the_fast_path_answers_as_the_route_does(admin, device, site, both_ways, route_calls, algorithm):  # noqa: F811
    model = train(admin, site, algorithm=algorithm)
    assert model["status"] == "ready", model
    url = f"/api/v1/sites/{site['id']}/locate"
    for body in _scans(12):
        before = len(route_calls)
        fast, route = both_ways(device, "POST", url, json=body)
        assert fast.status_code == 200, fast.text
        _same(fast, route)
        assert len(route_calls) == before + 1  # the second, fast path off; the first never reached the route
    fast, route = both_ways(device, "POST", url, json={**_scans(1)[0], "model_id": model["id"]})
    _same(fast, route)
    admin_key = httpx.Client(base_url=str(device.base_url), headers={"Authorization": f"Bearer {ADMIN_KEY}"})
    with admin_key:
        _same(*both_ways(admin_key, "POST", url, json=_scans(1)[0]))  # an admin key may do device work


def test_every_refusal_and_error_is_the_routes(admin, device, anonymous, site, both_ways, route_calls):  # noqa: F811
    url = f"/api/v1/sites/{site['id']}/locate"
    scan = _scans(1)[0]
    fast, route = both_ways(device, "POST", url, json=scan)  # no model yet: 409
    assert fast.status_code == 409
    _same(fast, route)
    train(admin, site, algorithm="wknn")
    raw = {"content": b'{"rss": {"wifi:x": -50}}'}
    cases = [
        (anonymous, "POST", url, {"json": scan}),  # 401: no key
        (anonymous, "POST", url, {"json": scan, "headers": {"Authorization": "Basic abc"}}),
        (anonymous, "POST", url, {"json": scan, "headers": {"Authorization": "Bearer"}}),
        (anonymous, "POST", url, {"json": scan, "headers": {"Authorization": "Bearer not-a-key"}}),
        (device, "POST", url, {"content": b"rss", "headers": {"Content-Type": "text/plain"}}),  # 415
        (device, "POST", url, {"content": b"{not json", "headers": {"Content-Type": "application/json"}}),  # 422
        (device, "POST", url, {"json": {}}),
        (device, "POST", url, {"json": {"rss": {}}}),
        (device, "POST", url, {"json": {"rss": {"wifi:x": "loud"}}}),
        (device, "POST", url, {"json": {**scan, "heading_deg": 1e9}}),
        (device, "POST", url, {"json": {**scan, "extra": 1}}),
        (device, "POST", url, {"json": {"rss": {"wifi:never-surveyed": -50.0}}}),  # 422: no known transmitter
        (device, "POST", url, {"json": {**scan, "model_id": 2**31 - 1}}),  # 404: no such model
        (device, "POST", url, {"json": {**scan, "model_id": 2**40}}),
        (device, "POST", url, {"json": scan, "headers": {"Content-Type": "application/vnd.x+json"}}),  # 200
        (device, "POST", url, {**raw, "headers": {"Content-Type": "application/json; charset=utf-8"}}),
        (device, "POST", "/api/v1/sites/2147483647/locate", {"json": scan}),  # 404: no such site
        (device, "POST", "/api/v1/sites/2147483648/locate", {"json": scan}),  # 422: beyond PathId
        (device, "POST", "/api/v1/sites/-2147483649/locate", {"json": scan}),
        (device, "POST", "/api/v1/sites/99999999999/locate", {"json": scan}),
        (device, "POST", f"/api/v1/sites/0{site['id']}/locate", {"json": scan}),  # 200, from the route
        (device, "POST", "/api/v1/sites/x/locate", {"json": scan}),
        (device, "GET", url, {}),  # 405
        (device, "POST", url, {"content": Chunked([b'{"rss": ', b'{"wifi:x": -50}}'])}),  # no declared length
    ]
    for client, method, where, kw in cases:
        fast, route = both_ways(client, method, where, **kw)
        assert fast.content == route.content, (where, kw.get("headers"), fast.text, route.text)
        _same(fast, route)


def test_a_stored_key_is_served_and_a_wrong_one_counted_once(admin, device, site, live_server, both_ways):  # noqa: F811
    train(admin, site, algorithm="knn")
    _, key = create_key(live_server.app.state.db, "phone", "device")
    url = f"/api/v1/sites/{site['id']}/locate"
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {key}"}) as stored:
        fast, route = both_ways(stored, "POST", url, json=_scans(1)[0])
        assert fast.status_code == 200
        _same(fast, route)
    failures = live_server.app.state.auth.failures
    since = time.monotonic()
    with httpx.Client(base_url=live_server.url, headers={"Authorization": "Bearer lk_wrong"}) as wrong:
        live_server.app.state.locate_fast_path = True
        assert wrong.post(url, json=_scans(1)[0]).status_code == 401
    assert failures_since(failures, since) == 1


def test_dependency_overrides_send_every_request_to_the_route(admin, device, site, live_server, route_calls):  # noqa: F811
    train(admin, site, algorithm="knn")
    app = live_server.app
    app.dependency_overrides[positioning_service] = lambda: app.state.positioning
    try:
        assert device.post(f"/api/v1/sites/{site['id']}/locate", json=_scans(1)[0]).status_code == 200
    finally:
        app.dependency_overrides.pop(positioning_service)
    assert len(route_calls) == 1
