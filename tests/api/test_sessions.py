"""Tracking sessions over real HTTP: open, feed, read, close; replay and ordering; bad input;
scope; persistence across a server restart; concurrent duplicates; crowdsourcing."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import httpx
import numpy as np
import pytest
from sqlalchemy import create_engine, text

from server.api.deps import session_service
from server.errors import Invalid
from server.estimation.tracking.selfcal import SEARCH_MARGIN_M
from server.estimation.types import Fix
from server.services.sessions import SessionService
from tests.conftest import LiveServer, make_settings

FLOORS = [
    {"level": 0, "walls": [[-50, -50, 50, -50]]},
    {"level": 1, "walls": []},
]
TRANSMITTERS = [
    {"id": "wifi:ap1", "kind": "wifi", "floor": 0, "x": 0.0, "y": 0.0},
    {"id": "wifi:ap2", "kind": "wifi", "floor": 0, "x": 10.0, "y": 0.0},
    {"id": "wifi:ap3", "kind": "wifi", "floor": 0, "x": 0.0, "y": 10.0},
    {"id": "wifi:up1", "kind": "wifi", "floor": 1, "x": 5.0, "y": 5.0},
]


@dataclass
class Located:
    fix: Fix
    model_id: int | None
    algorithm: str


class FakePositioning:
    """Stands in for the fingerprint model service: the fix is the RSS-weighted centroid of
    the heard transmitters with positions, on the floor most of them are on."""

    def __init__(self, positions: dict[str, tuple[float, float, int]], var: float = 0.25):
        self.positions, self.var, self.calls = positions, var, []

    def locate(self, site_id, rss, heading_deg=None, model_id=None, near=None, radius_m=None, serving=None):
        self.calls.append({"near": near, "radius_m": radius_m})
        known = {k: v for k, v in rss.items() if k in self.positions}
        if not known:
            raise Invalid("no transmitter in rss is known to the model")
        w = np.array([10 ** (v / 20) for v in known.values()])
        xy = np.array([self.positions[k][:2] for k in known])
        mean = (w[:, None] * xy).sum(0) / w.sum()
        floors = [self.positions[k][2] for k in known]
        floor = max(set(floors), key=floors.count)
        return Located(Fix(float(mean[0]), float(mean[1]), floor, np.eye(2) * self.var), model_id, "fake")


@pytest.fixture
def positioning(live_server):
    """Sessions served with a fake fingerprint model service (through the app's dependency overrides)."""
    fake = FakePositioning({t["id"]: (t["x"], t["y"], t["floor"]) for t in TRANSMITTERS})
    app = live_server.app
    service = SessionService(app.state.db, fake)
    app.dependency_overrides[session_service] = lambda: service
    yield fake
    app.dependency_overrides.pop(session_service)


@pytest.fixture
def site(admin) -> int:
    answer = admin.post("/api/v1/sites", json={"name": "lab", "floors": FLOORS, "transmitters": TRANSMITTERS})
    assert answer.status_code == 201, answer.text
    return answer.json()["id"]


def open_session(client, site, filter="kf", initial=True, **extra) -> dict:
    body = {"site_id": site, "filter": filter, **extra}
    if initial:
        body["initial"] = {"x": 1.0, "y": 2.0, "floor": 0, "heading_deg": 90.0}
    answer = client.post("/api/v1/sessions", json=body)
    assert answer.status_code == 201, answer.text
    return answer.json()


def steps(t0: float, n: int, heading: float = 90.0, length: float = 0.7) -> list[dict]:
    return [{"t": t0 + 0.5 * i, "length_m": length, "heading_deg": heading} for i in range(n)]


def batch(seq: int, t0: float, n_steps: int = 2, scans: list | None = None) -> dict:
    return {"seq": seq, "steps": steps(t0, n_steps), "scans": scans or []}


# --- the happy path ------------------------------------------------------------------------


def test_open_feed_read_close(device, site):
    session = open_session(device, site, "kf")
    assert session["status"] == "open" and session["filter"] == "kf" and session["site_id"] == site
    assert session["estimate"]["source"] == "init" and (session["estimate"]["x"], session["estimate"]["y"]) == (1.0, 2.0)
    sid = session["id"]

    first = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 4))
    assert first.status_code == 200, first.text
    result = first.json()
    assert result["seq"] == 0 and result["applied_steps"] == 4 and result["applied_scans"] == 0
    est = result["estimate"]
    assert est["source"] == "step" and est["t"] == 1.5 and est["floor"] == 0
    assert est["x"] == pytest.approx(1.0 + 4 * 0.7) and est["y"] == pytest.approx(2.0, abs=1e-9)  # heading 90 = +x

    second = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 2.0, 2)).json()
    assert second["estimate"]["x"] == pytest.approx(1.0 + 6 * 0.7)

    track = device.get(f"/api/v1/sessions/{sid}/track")
    assert track.status_code == 200
    sources = [e["source"] for e in track.json()]
    assert sources == ["init"] + ["step"] * 6
    # the initial estimate takes the time of the first input
    assert [e["t"] for e in track.json()] == [0.0, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5]

    got = device.get(f"/api/v1/sessions/{sid}").json()
    assert got["estimate"] == second["estimate"] and got["last_seq"] == 1 and got["track_length"] == 7

    assert device.delete(f"/api/v1/sessions/{sid}").status_code == 204
    assert device.get(f"/api/v1/sessions/{sid}").json()["status"] == "closed"
    closed = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(2, 3.0))
    assert closed.status_code == 409 and "closed" in closed.text
    # the track of a closed session can still be read
    assert len(device.get(f"/api/v1/sessions/{sid}/track").json()) == 7


@pytest.mark.parametrize("name", ["skpf", "ekf", "ukf", "kf", "pf", "fkf"])
def test_every_filter_runs_steps_and_scans(device, site, positioning, name):
    sid = open_session(device, site, name)["id"]
    scans = [{"t": 1.2, "rss": {"wifi:ap1": -50, "wifi:ap2": -60, "wifi:ap3": -60}}]
    answer = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 4, scans))
    assert answer.status_code == 200, answer.text
    r = answer.json()
    assert r["applied_steps"] == 4 and r["applied_scans"] == 1 and r["estimate"]["source"] == "step"
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert [e["source"] for e in track] == ["init", "step", "step", "step", "scan", "step"]
    call = positioning.calls[-1]
    if name == "fkf":  # fkf's search box restricts the model's candidates
        assert call["near"] is not None and call["radius_m"] == pytest.approx(9.0)
    elif name in ("ekf", "ukf", "skpf"):  # within 3σ + 10 m of the estimate before the scan
        before = track[3]
        assert call["near"] == pytest.approx((before["x"], before["y"]))
        assert call["radius_m"] > SEARCH_MARGIN_M
    else:  # the seed forms, and a pf on a floor with a plan (this one has a wall)
        assert call["near"] is None


def test_scans_pull_the_estimate_towards_the_fix(device, site, positioning):
    sid = open_session(device, site, "ekf", initial=False, )["id"]
    # no initial: steps before the first fix are dropped, the first scan starts the session
    b0 = {"seq": 0, "steps": steps(0.0, 3), "scans": [{"t": 2.0, "rss": {"wifi:ap2": -40, "wifi:ap1": -80}}]}
    r = device.post(f"/api/v1/sessions/{sid}/batches", json=b0).json()
    assert r["applied_steps"] == 0 and r["applied_scans"] == 1
    assert r["estimate"]["source"] == "scan" and r["estimate"]["x"] > 9
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert [e["source"] for e in track] == ["scan"]


def test_before_the_first_fix_the_estimate_is_null(device, site):
    sid = open_session(device, site, "skpf", initial=False)["id"]
    assert device.get(f"/api/v1/sessions/{sid}").json()["estimate"] is None
    r = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 3)).json()
    assert r["estimate"] is None and r["applied_steps"] == 0
    # without a fingerprint model, a scan of transmitters with no known position gives no fix
    scans = [{"t": 5.0, "rss": {"wifi:free": -50}}]
    r = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 3.0, 1, scans)).json()
    assert r["applied_scans"] == 0 and r["skipped_scans"][0]["index"] == 0
    assert device.get(f"/api/v1/sessions/{sid}/track").json() == []


def test_cold_start_without_a_model_multilaterates_from_positioned_transmitters(device, site):
    sid = open_session(device, site, "ekf", initial=False)["id"]
    rss = {"wifi:ap1": -45.0 - 25 * math.log10(5.0), "wifi:ap2": -45.0 - 25 * math.log10(5.0),
           "wifi:ap3": -45.0 - 25 * math.log10(math.hypot(5, 10))}  # truth (5, 0), default R0/γ
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": [{"t": 0.0, "rss": rss}]}).json()
    assert r["applied_scans"] == 1 and r["estimate"]["source"] == "scan" and r["estimate"]["floor"] == 0
    assert math.hypot(r["estimate"]["x"] - 5.0, r["estimate"]["y"]) < 1.0, r


def _cold_start_x(device, site) -> float:
    """x of the cold-start fix of a new session for a scan heard as if at (5, 0) by the
    transmitters' default R0/γ (no model: multilateration from their stored positions)."""
    sid = open_session(device, site, "ekf", initial=False)["id"]
    rss = {"wifi:ap1": -45.0 - 25 * math.log10(5.0), "wifi:ap2": -45.0 - 25 * math.log10(5.0),
           "wifi:ap3": -45.0 - 25 * math.log10(math.hypot(5, 10))}
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": [{"t": 0.0, "rss": rss}]}).json()
    assert r["applied_scans"] == 1, r
    return r["estimate"]["x"]


def test_moved_transmitters_and_a_recreated_site_are_seen_by_the_next_batch(admin, device, site):
    """Each process caches what fixes depend on per site revision: a change must show at once,
    and a new site that SQLite gives a deleted site's id must not inherit its cache."""
    assert abs(_cold_start_x(device, site) - 5.0) < 1.0
    moved = [{**t, "x": t["x"] + 20.0} for t in TRANSMITTERS]
    assert admin.put(f"/api/v1/sites/{site}/transmitters", json=moved).status_code == 200
    assert abs(_cold_start_x(device, site) - 25.0) < 1.0
    assert admin.delete(f"/api/v1/sites/{site}").status_code == 204
    again = admin.post("/api/v1/sites", json={"name": "lab again", "floors": FLOORS, "transmitters": TRANSMITTERS})
    assert again.status_code == 201, again.text
    assert abs(_cold_start_x(device, again.json()["id"]) - 5.0) < 1.0


def test_scan_with_no_known_transmitter_is_skipped_not_fatal(device, site, positioning):
    sid = open_session(device, site, "kf")["id"]
    scans = [{"t": 0.2, "rss": {"wifi:nobody": -50}}, {"t": 0.4, "rss": {"wifi:ap1": -50}}]
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "steps": [], "scans": scans}).json()
    assert r["applied_scans"] == 1 and [s["index"] for s in r["skipped_scans"]] == [0]
    assert "known" in r["skipped_scans"][0]["reason"]


def test_an_outlier_fix_is_reported_and_does_not_move_the_estimate(device, site, positioning):
    sid = open_session(device, site, "ekf")["id"]  # at (1, 2), 1 m²
    scans = [{"t": 0.5, "rss": {"wifi:ap3": -40.0}}]  # the fake model puts this at ap3: (0, 10)
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": scans}).json()
    assert r["applied_scans"] == 1 and [f["index"] for f in r["rejected_fixes"]] == [0]
    assert "outlier" in r["rejected_fixes"][0]["reason"]
    assert (r["estimate"]["x"], r["estimate"]["y"]) == pytest.approx((1.0, 2.0))


def test_a_refused_fix_is_marked_on_its_own_scan_when_the_scans_came_out_of_time_order(device, site, positioning):
    """Scans listed later-first: the one at t 0.5 (listed second) is applied first and refused;
    the track marks that scan's estimate, not the second one applied, and the answer's notes keep
    the contract's fields (the applied rank is stored, not sent)."""
    sid = open_session(device, site, "ekf")["id"]  # at (1, 2), 1 m²
    scans = [{"t": 1.0, "rss": {"wifi:ap1": -50.0}}, {"t": 0.5, "rss": {"wifi:ap3": -40.0}}]
    answer = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": scans}).json()
    assert answer["applied_scans"] == 2 and answer["rejected_fixes"][0]["index"] == 1
    assert [set(note) for note in answer["rejected_fixes"]] == [{"index", "reason"}]
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert [(e["t"], "fix_refused" in e) for e in track if e["source"] == "scan"] == [(0.5, True), (1.0, False)]


def test_a_landmark_snap_far_from_the_estimate_is_reported_and_replayed(admin, device, positioning):
    """A strong reading of a site's iBeacon 28 m from a confident estimate (a misplaced beacon): the
    self-calibrating tracker refuses the snap and the answer names it; a replay answers the same."""
    beacons = [*TRANSMITTERS, {"id": "ble:far", "kind": "ble", "floor": 0, "x": 0.0, "y": 30.0}]
    site = admin.post("/api/v1/sites", json={"name": "lab", "floors": FLOORS, "transmitters": beacons}).json()["id"]
    sid = open_session(device, site, "ekf")["id"]  # at (1, 2), 1 m²
    body = {"seq": 0, "scans": [{"t": 0.5, "rss": {"wifi:ap1": -50.0}}, {"t": 1.0, "rss": {"wifi:ap1": -50.0, "ble:far": -40.0}}]}
    r = device.post(f"/api/v1/sessions/{sid}/batches", json=body)
    assert r.status_code == 200, r.text
    answer = r.json()
    assert answer["rejected_fixes"] == [] and [n["index"] for n in answer["rejected_snaps"]] == [1]
    assert answer["rejected_snaps"][0]["reason"].startswith("landmark snap to ble:far ")
    assert "outlier" in answer["rejected_snaps"][0]["reason"]
    assert math.hypot(answer["estimate"]["x"], answer["estimate"]["y"] - 30.0) > 25.0  # not moved onto the beacon
    again = device.post(f"/api/v1/sessions/{sid}/batches", json=body)
    assert again.status_code == 200 and again.json() == answer
    # the track marks the scan whose snap was refused (and only that one), whole or paged
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    scans = [i for i, e in enumerate(track) if e["source"] == "scan"]
    assert [i for i, e in enumerate(track) if e.get("snap_refused")] == [scans[1]]
    assert not any("fix_refused" in e for e in track)
    page = device.get(f"/api/v1/sessions/{sid}/track", params={"since": scans[1] - 1, "limit": 1}).json()
    assert page == [track[scans[1]]]


def test_floor_changes_after_three_agreeing_fixes(device, site, positioning):
    sid = open_session(device, site, "kf")["id"]
    up = [{"t": 0.1 * (i + 1), "rss": {"wifi:up1": -40}} for i in range(3)]
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": up[:2]}).json()
    assert r["estimate"]["floor"] == 0  # hysteresis: two fixes upstairs are not enough
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 1, "scans": up[2:]}).json()
    assert r["estimate"]["floor"] == 1 and (r["estimate"]["x"], r["estimate"]["y"]) == pytest.approx((5.0, 5.0))


# --- replay and ordering ---------------------------------------------------------------------


def test_replayed_seq_gets_the_same_answer_and_is_not_applied_again(device, site, snapshot):
    sid = open_session(device, site, "pf")["id"]
    first = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 3))
    device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 2.0, 3))
    before = snapshot()
    again = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 3))
    assert again.status_code == 200 and again.json() == first.json()
    # even a replay with a different body is answered from the store and changes nothing
    other = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 7))
    assert other.json() == first.json()
    assert snapshot() == before
    assert len(device.get(f"/api/v1/sessions/{sid}/track").json()) == 1 + 6


def test_gap_is_accepted_and_the_missing_seq_is_then_409(device, site, snapshot):
    sid = open_session(device, site, "kf")["id"]
    assert device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0)).status_code == 200
    assert device.post(f"/api/v1/sessions/{sid}/batches", json=batch(2, 4.0)).status_code == 200  # seq 1 lost
    before = snapshot()
    late = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 2.0))
    assert late.status_code == 409 and late.json()["detail"][0]["field"] == "seq"
    assert snapshot() == before


def test_times_before_the_last_applied_time_are_422(device, site, snapshot):
    sid = open_session(device, site, "kf")["id"]
    device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 10.0, 2))  # last t = 10.5
    before = snapshot()
    older = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 10.0, 3))
    assert older.status_code == 422
    assert [d["field"] for d in older.json()["detail"]] == ["steps.0.t"]
    assert snapshot() == before
    # the same seq may then be sent again, corrected
    assert device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 10.5, 3)).status_code == 200


def test_steps_and_scans_are_applied_in_time_order(device, site, positioning):
    sid = open_session(device, site, "kf")["id"]
    body = {"seq": 0, "steps": [{"t": 3.0, "length_m": 0.5, "heading_deg": 0}, {"t": 1.0, "length_m": 0.5, "heading_deg": 0}],
            "scans": [{"t": 2.0, "rss": {"wifi:ap1": -50}}]}
    device.post(f"/api/v1/sessions/{sid}/batches", json=body)
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert [(e["source"], e["t"]) for e in track] == [("init", 1.0), ("step", 1.0), ("scan", 2.0), ("step", 3.0)]


# --- bad input ----------------------------------------------------------------------------------

BAD_BATCHES = [
    ({"seq": 0, "steps": [{"t": 0, "length_m": "NaN", "heading_deg": 0}]}, "steps.0.length_m"),
    ({"seq": 0, "steps": [{"t": float("inf"), "length_m": 0.7, "heading_deg": 0}]}, "steps.0.t"),
    ({"seq": 0, "steps": [{"t": 0, "length_m": -1, "heading_deg": 0}]}, "steps.0.length_m"),
    ({"seq": 0, "steps": [{"t": 0, "length_m": 0.7, "heading_deg": 1000}]}, "steps.0.heading_deg"),
    ({"seq": 0, "scans": [{"t": 0, "rss": {"wifi:ap1": 5}}]}, "scans.0.rss.wifi:ap1"),
    ({"seq": 0, "scans": [{"t": 0, "rss": {"wifi:ap1": -200}}]}, "scans.0.rss.wifi:ap1"),
    ({"seq": 0, "scans": [{"t": 0, "rss": {"WAP001": -50}}]}, "scans.0.rss"),
    ({"seq": 0, "scans": [{"t": 0, "rss": {}}]}, "scans.0.rss"),
    ({"seq": -1}, "seq"),
    ({"seq": 0, "steps": [], "extra": 1}, "extra"),
    ({"steps": []}, "seq"),
]


@pytest.mark.parametrize("body, field", BAD_BATCHES)
def test_bad_batches_are_422_naming_the_field_and_change_nothing(device, site, snapshot, body, field):
    sid = open_session(device, site, "kf")["id"]
    before = snapshot()
    answer = device.post(f"/api/v1/sessions/{sid}/batches", content=_json(body), headers={"Content-Type": "application/json"})
    assert answer.status_code == 422, answer.text
    assert any(d["field"].startswith(field) for d in answer.json()["detail"]), answer.json()
    assert snapshot() == before


def _json(body) -> str:
    import json

    return json.dumps(body)  # allow NaN/Infinity literals, as a careless client would send


@pytest.mark.parametrize("key", ["steps", "scans"])
def test_too_many_steps_or_scans_is_413(device, site, snapshot, key):
    sid = open_session(device, site, "kf")["id"]
    item = {"t": 0, "length_m": 0.5, "heading_deg": 0} if key == "steps" else {"t": 0, "rss": {"wifi:ap1": -50}}
    before = snapshot()
    answer = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, key: [item] * 1001})
    assert answer.status_code == 413 and answer.json()["detail"][0]["field"] == key
    assert snapshot() == before


BAD_OPENS = [
    ({"filter": "nope"}, 422, "filter"),
    ({"filter": "kf", "initial": {"x": 0, "y": 0, "floor": 7}}, 422, "initial.floor"),
    ({"filter": "kf", "initial": {"x": 0, "y": 0, "floor": 0, "covariance": [[1, 0], [0, -1]]}}, 422, "initial.covariance"),
    ({"filter": "kf", "initial": {"x": "NaN", "y": 0, "floor": 0}}, 422, "initial.x"),
    ({"filter": "kf", "model_id": 999}, 422, "model_id"),
]


@pytest.mark.parametrize("extra, code, field", BAD_OPENS)
def test_bad_opens_are_rejected_naming_the_field(device, site, snapshot, extra, code, field):
    before = snapshot()
    answer = device.post("/api/v1/sessions", content=_json({"site_id": site, **extra}),
                         headers={"Content-Type": "application/json"})
    assert answer.status_code == code, answer.text
    detail = answer.json()["detail"]
    assert any(d.get("field") == field for d in detail), detail
    assert snapshot() == before


def test_unknown_site_or_session_is_404(device, site):
    assert device.post("/api/v1/sessions", json={"site_id": site + 100, "filter": "kf"}).status_code == 404
    for method, path, body in _session_endpoints("no-such-session"):
        assert device.request(method, path, json=body).status_code == 404


# --- scope ------------------------------------------------------------------------------------


def _session_endpoints(sid: str):
    return [
        ("POST", f"/api/v1/sessions/{sid}/batches", batch(0, 0.0)),
        ("GET", f"/api/v1/sessions/{sid}", None),
        ("GET", f"/api/v1/sessions/{sid}/track", None),
        ("DELETE", f"/api/v1/sessions/{sid}", None),
    ]


def test_sessions_need_a_key(anonymous, device, site, snapshot):
    sid = open_session(device, site)["id"]
    before = snapshot()
    assert anonymous.post("/api/v1/sessions", json={"site_id": site, "filter": "kf"}).status_code == 401
    for method, path, body in _session_endpoints(sid):
        assert anonymous.request(method, path, json=body).status_code == 401
        assert anonymous.request(method, path, json=body, headers={"Authorization": "Bearer nope"}).status_code == 401
    assert snapshot() == before


def test_another_device_cannot_see_or_feed_a_session_but_an_admin_can(live_server, device, admin, site, snapshot):
    from server.auth import create_key
    from server.db import Database

    db = Database(live_server.app.state.settings.database_url)
    _, other_key = create_key(db, "phone 2", "device")
    db.dispose()
    sid = open_session(device, site)["id"]
    device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0))
    before = snapshot()
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {other_key}"}) as other:
        for method, path, body in _session_endpoints(sid):
            answer = other.request(method, path, json=body)
            assert answer.status_code == 404, (method, path, answer.text)
    assert snapshot() == before
    assert admin.get(f"/api/v1/sessions/{sid}").json()["last_seq"] == 0
    assert len(admin.get(f"/api/v1/sessions/{sid}/track").json()) == 3
    # admin keys may open and feed sessions too
    mine = open_session(admin, site)["id"]
    assert admin.post(f"/api/v1/sessions/{mine}/batches", json=batch(0, 0.0)).status_code == 200
    assert device.get(f"/api/v1/sessions/{mine}").status_code == 404


def test_a_device_lists_its_own_sessions_newest_first_and_an_admin_lists_all(live_server, device, admin, site):
    from server.auth import create_key
    from server.db import Database

    db = Database(live_server.app.state.settings.database_url)
    _, other_key = create_key(db, "phone 3", "device")
    db.dispose()
    first, second = open_session(device, site)["id"], open_session(device, site)["id"]
    assert device.delete(f"/api/v1/sessions/{first}").status_code == 204
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {other_key}"}) as other:
        theirs = open_session(other, site)["id"]
        assert [x["id"] for x in other.get("/api/v1/sessions").json()] == [theirs]
    assert [x["id"] for x in device.get("/api/v1/sessions").json()] == [second, first]
    assert [x["id"] for x in device.get("/api/v1/sessions", params={"status": "open"}).json()] == [second]
    assert [x["id"] for x in device.get("/api/v1/sessions", params={"limit": 1}).json()] == [second]
    assert device.get("/api/v1/sessions", params={"site_id": site + 1}).json() == []
    assert {x["id"] for x in admin.get("/api/v1/sessions").json()} == {first, second, theirs}
    for bad in ({"limit": 0}, {"limit": 1001}, {"status": "done"}):
        answer = device.get("/api/v1/sessions", params=bad)
        assert answer.status_code == 422 and next(iter(bad)) in answer.text


# --- persistence and concurrency ---------------------------------------------------------------


def test_a_batch_the_tracker_fails_on_is_refused_and_the_session_goes_on(device, site, monkeypatch):
    """A numerical failure inside the tracker (injected here: its prediction raises LinAlgError) is a 422
    naming it, not a 500; nothing of that batch is stored, and the phone's next batch applies."""
    from server.estimation.tracking.ekf import EKFTracker

    sid = open_session(device, site, "ekf")["id"]
    assert device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0)).status_code == 200
    session_before = device.get(f"/api/v1/sessions/{sid}").json()
    track_before = device.get(f"/api/v1/sessions/{sid}/track").json()

    def singular(self, *args, **kwargs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(EKFTracker, "predict", singular)
    answer = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 2.0))
    assert answer.status_code == 422, answer.text
    assert "ekf tracker could not apply" in answer.text and "LinAlgError" in answer.text
    assert device.get(f"/api/v1/sessions/{sid}").json() == session_before
    assert device.get(f"/api/v1/sessions/{sid}/track").json() == track_before

    monkeypatch.undo()
    assert device.post(f"/api/v1/sessions/{sid}/batches", json=batch(2, 4.0)).status_code == 200
    assert device.get(f"/api/v1/sessions/{sid}").json()["last_seq"] == 2
    assert len(device.get(f"/api/v1/sessions/{sid}/track").json()) == len(track_before) + 2


def test_a_smoother_that_fails_numerically_is_a_409_and_the_live_track_stays(device, site, monkeypatch):
    """The RTS recursion inverts each predicted covariance; should one be singular (injected here) the
    smoothed track is a 409 naming the failure, not a 500, and the live track reads as before."""
    from server.estimation.tracking import smoother

    sid = open_session(device, site, "ekf")["id"]
    for i in range(3):
        assert device.post(f"/api/v1/sessions/{sid}/batches", json=batch(i, 2.0 * i)).status_code == 200
    live = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"}).status_code == 200

    def singular(*args, **kwargs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(smoother, "_rts", singular)
    answer = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"})
    assert answer.status_code == 409, answer.text
    assert "could not be smoothed" in answer.text and "LinAlgError" in answer.text and "smoothed" in answer.text
    assert device.get(f"/api/v1/sessions/{sid}/track").json() == live


def test_a_session_survives_a_server_restart_mid_walk(live_server, device, site, clean_db):
    sid = open_session(device, site, "skpf")["id"]
    answers = [device.post(f"/api/v1/sessions/{sid}/batches", json=batch(i, 2.0 * i, 3)).json() for i in range(3)]
    track_before = device.get(f"/api/v1/sessions/{sid}/track").json()

    # a fresh process (new app, new engine, nothing in memory) on the same database
    second = LiveServer(make_settings(clean_db)).start()
    try:
        with httpx.Client(base_url=second.url, headers=dict(device.headers)) as phone:
            assert phone.get(f"/api/v1/sessions/{sid}/track").json() == track_before
            assert phone.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 2.0, 3)).json() == answers[1]
            r3 = phone.post(f"/api/v1/sessions/{sid}/batches", json=batch(3, 6.0, 3))
            assert r3.status_code == 200
    finally:
        second.stop()
    # the first server continues where the second stopped
    r4 = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(4, 8.0, 3)).json()
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert len(track) == 1 + 5 * 3 and track[:len(track_before)] == track_before
    assert r4["estimate"] == track[-1]
    assert r4["estimate"]["x"] == pytest.approx(1.0 + 15 * 0.7, abs=1.5)
    state = _state(clean_db, sid)  # the tracker lives in the database, particles and RNG included
    assert state["tracker"]["filter"] == "skpf" and state["estimate"] == r4["estimate"]


def _state(url: str, sid: str) -> dict:
    import json

    engine = create_engine(url)
    with engine.connect() as conn:
        raw = conn.execute(text("SELECT state FROM tracking_sessions WHERE id = :i"), {"i": sid}).scalar()
    engine.dispose()
    return raw if isinstance(raw, dict) else json.loads(raw)


def test_concurrent_duplicate_posts_apply_once(live_server, device, site):
    sid = open_session(device, site, "skpf")["id"]
    device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 2))
    answers, barrier = [], threading.Barrier(8)

    def post():
        with httpx.Client(base_url=live_server.url, headers=dict(device.headers), timeout=60) as c:
            barrier.wait()
            answers.append(c.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 1.0, 5)))

    threads = [threading.Thread(target=post) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert [a.status_code for a in answers] == [200] * 8
    assert len({a.text for a in answers}) == 1
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert len(track) == 1 + 2 + 5


def test_concurrent_different_seqs_all_apply_without_loss(live_server, device, site):
    """Batches of one session sent at once: each is applied once or refused with 409 (below
    the last applied seq), never lost silently, never doubled."""
    sid = open_session(device, site, "kf")["id"]
    codes = {}

    def post(seq):
        with httpx.Client(base_url=live_server.url, headers=dict(device.headers), timeout=60) as c:
            codes[seq] = c.post(f"/api/v1/sessions/{sid}/batches", json=batch(seq, 2.0 * seq, 2)).status_code

    threads = [threading.Thread(target=post, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    applied = sorted(s for s, c in codes.items() if c == 200)
    assert all(c in (200, 409, 422) for c in codes.values())
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert len(track) == 1 + 2 * len(applied)
    assert [e["t"] for e in track[1:]] == sorted(e["t"] for e in track[1:])


# --- crowdsourcing ------------------------------------------------------------------------------


def _crowd_rows(url: str) -> list[tuple]:
    engine = create_engine(url)
    with engine.connect() as conn:
        rows = conn.execute(text("SELECT x, y, floor, samples FROM fingerprints WHERE source = 'crowd' ORDER BY id")).all()
    engine.dispose()
    return [tuple(r) for r in rows]


CONFIDENT_SCAN = {"wifi:ap1": -45.0, "wifi:ap2": -70.0, "wifi:ap3": -70.0}


def _walk_in_place(device, site, n_batches: int, filter="kf"):
    sid = open_session(device, site, filter)["id"]
    for i in range(n_batches):
        scans = [{"t": 1.0 * i + 0.5, "rss": CONFIDENT_SCAN}]
        r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": i, "scans": scans})
        assert r.status_code == 200 and r.json()["applied_scans"] == 1
    return sid


def test_crowdsourcing_off_stores_nothing(device, site, positioning, clean_db):
    _walk_in_place(device, site, 4)
    assert _crowd_rows(clean_db) == []


def test_crowdsourcing_on_stores_and_merges_crowd_points(admin, device, site, positioning, clean_db):
    answer = admin.patch(f"/api/v1/sites/{site}", json={"settings": {"crowdsourcing": True}})
    assert answer.status_code == 200 and answer.json()["settings"] == {"crowdsourcing": True}
    assert device.patch(f"/api/v1/sites/{site}", json={"settings": {"crowdsourcing": False}}).status_code == 403
    _walk_in_place(device, site, 6)
    rows = _crowd_rows(clean_db)
    # the estimate converges onto the fix; the confident ones all land within 1 m: merged into one point
    assert len(rows) == 1 and rows[0][3] >= 3, rows
    assert admin.get(f"/api/v1/sites/{site}").json()["fingerprints"]["crowd"] == 1


def test_turning_crowdsourcing_on_mid_session_applies_from_the_next_batch(admin, device, site, positioning, clean_db):
    sid = _walk_in_place(device, site, 3)
    assert _crowd_rows(clean_db) == []
    assert admin.patch(f"/api/v1/sites/{site}", json={"settings": {"crowdsourcing": True}}).status_code == 200
    scans = [{"t": 10.5, "rss": CONFIDENT_SCAN}]
    assert device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 3, "scans": scans}).status_code == 200
    assert len(_crowd_rows(clean_db)) == 1


def test_crowdsourcing_gate_refuses_uncertain_estimates(admin, device, site, positioning, clean_db):
    admin.patch(f"/api/v1/sites/{site}", json={"settings": {"crowdsourcing": True}})
    positioning.var = 25.0  # a vague fix: the estimate stays uncertain (trace > 2 m²)
    initial = {"x": 0.5, "y": 0.5, "floor": 0, "covariance": [[4, 0], [0, 4]]}
    sid = device.post("/api/v1/sessions", json={"site_id": site, "filter": "ekf", "initial": initial}).json()["id"]
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": [{"t": 0.5, "rss": CONFIDENT_SCAN}]})
    assert r.json()["applied_scans"] == 1 and np.trace(r.json()["estimate"]["covariance"]) > 2.0
    assert _crowd_rows(clean_db) == []


def test_the_cold_start_scan_is_not_crowdsourced(admin, device, site, positioning, clean_db):
    """The first fix of a session without initial is the estimate itself: no independent check."""
    admin.patch(f"/api/v1/sites/{site}", json={"settings": {"crowdsourcing": True}})
    sid = open_session(device, site, "kf", initial=False)["id"]
    r = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": [{"t": 0.5, "rss": CONFIDENT_SCAN}]})
    assert r.json()["applied_scans"] == 1
    assert _crowd_rows(clean_db) == []


def test_site_settings_reject_unknown_keys(admin, site, snapshot):
    before = snapshot()
    answer = admin.patch(f"/api/v1/sites/{site}", json={"settings": {"crowd": True}})
    assert answer.status_code == 422 and "crowd" in answer.text
    assert snapshot() == before


def test_a_batch_that_fails_mid_write_leaves_nothing_and_can_be_resent(device, site, snapshot, monkeypatch):
    """State, last seq, answer and estimates commit together: a failure after the
    compare-and-set (here: storing the estimates) rolls all of it back."""
    import server.store.sessions as store

    sid = open_session(device, site, "ekf")["id"]
    device.post(f"/api/v1/sessions/{sid}/batches", json=batch(0, 0.0, 2))
    before = snapshot()
    real = store._estimate_rows
    calls = []

    def broken(*args, **kwargs):
        calls.append(1)
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(store, "_estimate_rows", broken)
    failed = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 1.0, 2))
    assert failed.status_code == 500 and failed.json() == {"detail": "internal server error"}
    assert calls
    assert snapshot() == before
    monkeypatch.setattr(store, "_estimate_rows", real)
    again = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(1, 1.0, 2))
    assert again.status_code == 200 and again.json()["applied_steps"] == 2
    assert len(device.get(f"/api/v1/sessions/{sid}/track").json()) == 1 + 4
