"""The dashboard in a real headless Chromium against the live test server: it loads without a
console error, asks for the key once, draws the site's walls, reference points and
transmitters, and a session a client posts appears on the map and moves; a device key sees
only its own sessions; the API docs pages load their assets from the app."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.conftest import ADMIN_KEY, DEVICE_KEY

pytestmark = pytest.mark.browser

SITE = {
    "name": "browser lab",
    "floors": [
        {"level": 0, "name": "ground", "width_m": 20, "height_m": 12,
         "walls": [[0, 0, 20, 0], [20, 0, 20, 12], [20, 12, 0, 12], [0, 12, 0, 0], [10, 0, 10, 7]]},
        {"level": 1, "walls": []},
    ],
    "transmitters": [
        {"id": "wifi:aa:bb:cc:dd:ee:01", "kind": "wifi", "floor": 0, "x": 2.0, "y": 2.0},
        {"id": "wifi:aa:bb:cc:dd:ee:02", "kind": "wifi", "floor": 0, "x": 18.0, "y": 10.0},
        {"id": "ble:f7826da6-4fa2-4e98-8024-bc5b71e0893e:1:1", "kind": "ble", "floor": 0, "x": 15.0, "y": 3.0},
    ],
}
RPS = [(2.0, 3.0), (5.0, 3.0), (8.0, 3.0), (14.0, 9.0), (17.0, 9.0)]


@pytest.fixture
def site(admin) -> int:
    answer = admin.post("/api/v1/sites", json=SITE)
    assert answer.status_code == 201, answer.text
    sid = answer.json()["id"]
    fps = [
        {"x": x, "y": y, "floor": 0, "label": f"rp{i}", "rss": {"wifi:aa:bb:cc:dd:ee:01": -40.0 - 2 * x - k}}
        for i, (x, y) in enumerate(RPS) for k in range(i + 1)
    ]
    answer = admin.post(f"/api/v1/sites/{sid}/surveys", json={"fingerprints": fps})
    assert answer.status_code in (200, 201), answer.text
    return sid


@pytest.fixture(autouse=True)
def fast_streams(live_server):
    state = live_server.app.state
    state.events_poll_s = 0.05
    yield
    del state.events_poll_s


def login(page, url: str, key: str) -> None:
    page.goto(url + "/")
    page.fill("#key", key)
    page.click("#login-form button[type=submit]")
    page.wait_for_selector("#app:not([hidden])")


def feed(client, sid: str, seq: int, n: int, t0: float) -> None:
    steps = [{"t": t0 + 0.5 * i, "length_m": 0.7, "heading_deg": 90.0} for i in range(n)]
    answer = client.post(f"/api/v1/sessions/{sid}/batches", json={"seq": seq, "steps": steps})
    assert answer.status_code == 200, answer.text


@contextmanager
def scripted_fixes(app, fixes=()) -> Iterator:
    """The app's sessions locate with a scripted fingerprint service (its fixes in order, σ² 0.5),
    for what the block posts; the real service again after it."""
    from server.api.deps import session_service
    from server.services.sessions import SessionService
    from tests.api.test_sessions_smoothed import ScriptedPositioning

    fake = ScriptedPositioning(var=0.5)
    fake.fixes.extend(fixes)
    app.dependency_overrides[session_service] = lambda: SessionService(app.state.db, fake)
    try:
        yield fake
    finally:
        app.dependency_overrides.pop(session_service)


def replay(page, sid: str) -> None:
    """Click a listed session and wait until its stored track is replayed."""
    page.click(f"#sessions li[data-session='{sid}']")
    page.wait_for_function("document.getElementById('status').textContent.startsWith('replayed')", timeout=10_000)


def position(page, sid: str) -> tuple[float, float]:
    dot = page.locator(f"circle.pos[data-session='{sid}']")
    return float(dot.get_attribute("cx")), float(dot.get_attribute("cy"))


def test_coverage_is_modelled_on_a_floor_without_survey(page, live_server, site, admin):
    tx = {"id": "wifi:aa:bb:cc:dd:ee:03", "kind": "wifi", "floor": 1, "x": 5.0, "y": 5.0}
    assert admin.put(f"/api/v1/sites/{site}/transmitters", json=[tx]).status_code == 200
    login(page, live_server.url, ADMIN_KEY)
    page.wait_for_selector("circle.rp")
    page.select_option("#floor", "0:1")  # (building 0, level 1)
    page.select_option("#coverage", tx["id"])
    page.wait_for_selector("#coverage-layer.modelled rect.heat")
    assert page.locator("rect.heat").count() > 100 and page.locator("circle.cov").count() == 0
    assert page.locator("#coverage-legend").is_visible() and "modelled" in page.text_content("#coverage-legend")
    assert not page.locator("#coverage-measured-legend").is_visible()
    assert page.errors == []


def test_dashboard_map_and_live_session(page, live_server, site, device):
    login(page, live_server.url, ADMIN_KEY)
    assert page.text_content("#scope") == "admin key"
    page.wait_for_selector("circle.rp")
    assert page.locator("circle.rp").count() == len(RPS)
    labels = {page.locator("circle.rp").nth(i).get_attribute("data-label") for i in range(len(RPS))}
    assert labels == {f"rp{i}" for i in range(len(RPS))}
    # reference points are sized by their fingerprint counts (rp4 has 5, rp0 has 1)
    radius = {c.get_attribute("data-label"): float(c.get_attribute("r")) for c in page.locator("circle.rp").all()}
    assert radius["rp4"] > radius["rp0"]
    assert page.locator("line.wall").count() == 5
    assert page.locator(".tx.wifi").count() == 2 and page.locator(".tx.ble").count() == 1
    # the measured coverage of a surveyed transmitter: a disc per reference point coloured by its
    # mean RSS (rp{i} at x heard -40 - 2x - k for k < i + 1), with the dBm scale in the legend
    page.select_option("#coverage", "wifi:aa:bb:cc:dd:ee:01")
    page.wait_for_selector("#coverage-layer.measured circle.cov")
    cov = {c.get_attribute("data-label"): c for c in page.locator("circle.cov").all()}
    assert set(cov) == {f"rp{i}" for i in range(len(RPS))}
    for i, (x, _) in enumerate(RPS):
        assert float(cov[f"rp{i}"].get_attribute("data-rss")) == pytest.approx(-40.0 - 2 * x - i / 2, abs=0.05)
    assert page.locator("circle.cov.not-heard").count() == 0 and page.locator("rect.heat").count() == 0
    assert cov["rp0"].get_attribute("fill") != cov["rp4"].get_attribute("fill")
    assert page.locator("#coverage-measured-legend").is_visible() and not page.locator("#coverage-legend").is_visible()
    assert "dBm" in page.text_content("#coverage-measured-legend")
    # a transmitter no fingerprint heard: every reference point "not heard"
    page.select_option("#coverage", "wifi:aa:bb:cc:dd:ee:02")
    page.wait_for_function("document.querySelectorAll('circle.cov.not-heard').length === 5")
    assert page.locator("circle.cov.heard").count() == 0
    page.select_option("#coverage", "")
    assert page.locator("circle.cov").count() == 0 and page.locator("rect.heat").count() == 0
    assert not page.locator("#coverage-measured-legend").is_visible()
    assert "1 · " not in page.text_content("#floor") or page.locator("#floor option").count() == 2

    # a session posted by a client appears live, with its covariance ellipse, and moves
    body = {"site_id": site, "filter": "kf", "initial": {"x": 3.0, "y": 5.0, "floor": 0}}
    sid = device.post("/api/v1/sessions", json=body).json()["id"]
    page.wait_for_selector(f"circle.pos[data-session='{sid}']", timeout=10_000)
    assert page.locator(f"g.session[data-session='{sid}'] ellipse").count() == 1
    x0, y0 = position(page, sid)
    assert (x0, y0) == pytest.approx((3.0, -5.0))  # SVG y is north flipped
    feed(device, sid, 0, 4, 0.0)
    page.wait_for_function(
        f"document.querySelector(\"circle.pos[data-session='{sid}']\").dataset.idx === '4'", timeout=10_000
    )
    x1, y1 = position(page, sid)
    assert x1 == pytest.approx(3.0 + 4 * 0.7, abs=1e-6) and y1 == pytest.approx(-5.0, abs=1e-6)  # heading 90 = east
    page.wait_for_selector(f"#sessions li[data-session='{sid}']")

    # closed: the list says so, and clicking it replays the stored track
    device.delete(f"/api/v1/sessions/{sid}")
    page.click("#refresh-sessions")
    page.wait_for_selector(f"#sessions li[data-session='{sid}'] >> text=closed")
    replay(page, sid)
    assert position(page, sid) == pytest.approx((x1, y1))
    # beside the live track, the smoothed one (a toggle)
    smoothed = page.locator(f"polyline.track.smoothed[data-session='{sid}']")
    assert smoothed.count() == 1 and len(smoothed.get_attribute("points").split()) == 5
    page.uncheck("#show-smoothed")
    assert smoothed.count() == 0 and page.locator(f"g.session[data-session='{sid}'] polyline.live").count() == 1
    page.check("#show-smoothed")
    assert smoothed.count() == 1

    shot = os.environ.get("LOCALIZER_DASHBOARD_SCREENSHOT")
    if shot:
        Path(shot).parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=shot)
    assert page.errors == []


def test_dashboard_device_key_sees_own_sessions(page, live_server, site, device, admin):
    admin_sid = admin.post("/api/v1/sessions", json={"site_id": site, "filter": "kf"}).json()["id"]
    body = {"site_id": site, "filter": "kf", "initial": {"x": 1.0, "y": 1.0, "floor": 0}}
    sid = device.post("/api/v1/sessions", json=body).json()["id"]
    login(page, live_server.url, DEVICE_KEY)
    assert page.text_content("#scope") == "device key"
    assert page.locator("#sites-panel").is_hidden() and page.locator("#models-panel").is_hidden()
    page.wait_for_selector(f"circle.pos[data-session='{sid}']", timeout=10_000)
    feed(device, sid, 0, 2, 0.0)
    page.wait_for_function(
        f"document.querySelector(\"circle.pos[data-session='{sid}']\").dataset.idx === '2'", timeout=10_000
    )
    assert page.locator(f"#sessions li[data-session='{admin_sid}']").count() == 0
    # the key is kept for the tab: a reload does not ask again
    page.reload()
    page.wait_for_selector("#app:not([hidden])")
    assert page.locator("#login").is_hidden()
    assert page.errors == []


def test_wrong_key_is_asked_again(page, live_server, clean_db):
    page.goto(live_server.url + "/")
    page.fill("#key", "not-a-key")
    page.click("#login-form button[type=submit]")
    page.wait_for_function("document.getElementById('login-error').textContent.includes('refused')")
    assert page.locator("#app").is_hidden()
    assert all("401" in e for e in page.errors)  # the refused request itself, nothing else


@pytest.mark.parametrize("path", ["/docs", "/redoc"])
def test_docs_render_offline(page, live_server, path):
    """Swagger UI and ReDoc come from the app; every request the page makes is answered by it
    (ReDoc's CDN logo is refused by the page's content security policy)."""
    requests: list[str] = []
    page.on("requestfinished", lambda r: requests.append(r.url))
    page.goto(live_server.url + path)
    page.wait_for_selector(".swagger-ui .info .title" if path == "/docs" else "redoc-wrap, .api-content", timeout=20_000)
    assert "Localizer" in page.content()
    outside = [u for u in requests if not u.startswith((live_server.url, "data:", "blob:"))]
    assert requests and not outside, outside


def test_replay_draws_the_smoothed_track_and_marks_refused_fixes(page, live_server, site, device):
    """A walk east with a fix every 2 steps (scripted fingerprint service), one of them 9 m off:
    the replay draws the smoothed path beside the live one and a cross at the refused fix."""
    with scripted_fixes(live_server.app) as fake:
        body = {"site_id": site, "filter": "kf", "initial": {"x": 2.0, "y": 5.0, "floor": 0}}
        sid = device.post("/api/v1/sessions", json=body).json()["id"]
        steps, scans = [], []
        for i in range(16):
            steps.append({"t": 0.5 * (i + 1), "length_m": 0.75, "heading_deg": 85.0})
            if i % 2 == 1:
                off = 9.0 if len(scans) == 4 else 0.0
                fake.fixes.append((2.0 + 0.7 * (i + 1), 5.0 + off))
                scans.append({"t": 0.5 * (i + 1) + 0.25, "rss": {"wifi:aa:bb:cc:dd:ee:01": -50.0}})
        answer = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "steps": steps, "scans": scans})
        assert [f["index"] for f in answer.json()["rejected_fixes"]] == [4]
        device.delete(f"/api/v1/sessions/{sid}")
    login(page, live_server.url, ADMIN_KEY)
    replay(page, sid)
    live = page.locator(f"g.session[data-session='{sid}'] polyline.live").get_attribute("points")
    smoothed = page.locator(f"polyline.track.smoothed[data-session='{sid}']").get_attribute("points")
    assert len(smoothed.split()) == len(live.split()) == 1 + 16 + 8 and smoothed != live
    marks = page.locator(f"path.refused[data-session='{sid}']")
    assert marks.count() == 1 and marks.get_attribute("data-idx") == str(1 + 10 + 4)  # init, 10 steps, 5th scan
    assert page.locator("#legend").text_content().count("smoothed track") == 1
    assert page.errors == []


def test_replay_marks_a_refused_landmark_snap(page, live_server, site, device):
    """A strong reading of the site's iBeacon 13 m from a confident estimate: the gate refuses
    the snap, and the replay draws a diamond at that scan's estimate (and no refused-fix cross)."""
    with scripted_fixes(live_server.app, [(2.5, 5.0), (3.0, 5.0)]):
        body = {"site_id": site, "filter": "ekf", "initial": {"x": 2.0, "y": 5.0, "floor": 0}}
        sid = device.post("/api/v1/sessions", json=body).json()["id"]
        wifi = {"wifi:aa:bb:cc:dd:ee:01": -50.0}
        scans = [{"t": 0.5, "rss": wifi}, {"t": 1.0, "rss": {**wifi, SITE["transmitters"][2]["id"]: -40.0}}]
        answer = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": scans}).json()
        assert [n["index"] for n in answer["rejected_snaps"]] == [1] and answer["rejected_fixes"] == []
        device.delete(f"/api/v1/sessions/{sid}")
    login(page, live_server.url, ADMIN_KEY)
    replay(page, sid)
    marks = page.locator(f"path.snap-refused[data-session='{sid}']")
    assert marks.count() == 1 and marks.get_attribute("data-idx") == "2"  # init, first scan, second scan
    assert page.locator(f"path.refused[data-session='{sid}']").count() == 0
    assert "landmark snap refused" in page.locator("#legend").text_content()
    assert page.errors == []
