"""The smoothed track (`GET /api/v1/sessions/{id}/track?smoothed=true`) and the refused fixes
marked on a track (`fix_refused`), over real HTTP with a scripted fingerprint service."""

from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import replace

import numpy as np
import pytest
from sqlalchemy import select, text, update

from server.api.deps import session_service
from server.errors import Invalid
from server.estimation.replay import smoothed_by_replay
from server.estimation.tracking.smoother import smooth_track
from server.estimation.types import Estimate, Fix, FullState
from server.schemas import EstimateOut
from server.services import sessions as sessions_service
from server.services.sessions import SessionService
from server.tables import SessionBatch, TrackEstimate, TrackingSession
from tests.api.test_sessions import FLOORS, TRANSMITTERS, Located

STEP_S, LENGTH_M, N_STEPS, SCAN_EVERY = 0.5, 0.7, 60, 4


class ScriptedPositioning:
    """The fingerprint service as a script: each fix asked for is the next one queued (a
    session with `initial` asks once per scan, in time order)."""

    def __init__(self, var: float = 1.0):
        self.var, self.fixes = var, deque()

    def locate(self, site_id, rss, heading_deg=None, model_id=None, near=None, radius_m=None, serving=None):
        if not self.fixes:
            raise Invalid("no fix scripted")
        x, y = self.fixes.popleft()
        return Located(Fix(float(x), float(y), 0, np.eye(2) * self.var), model_id, "scripted")


@pytest.fixture
def scripted(live_server):
    fake = ScriptedPositioning()
    app = live_server.app
    app.dependency_overrides[session_service] = lambda: SessionService(app.state.db, fake)
    yield fake
    app.dependency_overrides.pop(session_service)


@pytest.fixture
def site(admin) -> int:
    answer = admin.post("/api/v1/sites", json={"name": "lab", "floors": FLOORS, "transmitters": TRANSMITTERS})
    assert answer.status_code == 201, answer.text
    return answer.json()["id"]


def _walk(device, site, scripted, outlier_at: int | None = None,
          filter: str = "kf") -> tuple[str, dict[float, tuple[float, float]]]:
    """A walk east from (1, 2) along y = 2 whose steps say 8° left of the truth and 10 % long
    (PDR drift), with a fix (σ 1 m) every 4 steps; returns the session id and the truth at each
    input time."""
    rng = np.random.default_rng(7)
    sid = device.post("/api/v1/sessions", json={"site_id": site, "filter": filter,
                                                "initial": {"x": 1.0, "y": 2.0, "floor": 0}}).json()["id"]
    truth = {0.0: (1.0, 2.0)}
    steps, scans = [], []
    for i in range(N_STEPS):
        t = STEP_S * (i + 1)
        x = 1.0 + LENGTH_M * (i + 1)
        truth[t] = (x, 2.0)
        steps.append({"t": t, "length_m": LENGTH_M * 1.1 + rng.normal(0, 0.03),
                      "heading_deg": 90.0 - 8.0 + rng.normal(0, 2.0)})
        if (i + 1) % SCAN_EVERY == 0:
            ts = t + STEP_S / 2
            truth[ts] = (x, 2.0)
            n = len(scans)
            fx, fy = (x, 2.0 + 15.0) if n == outlier_at else (x + rng.normal(0, 1.0), 2.0 + rng.normal(0, 1.0))
            scripted.fixes.append((fx, fy))
            scans.append({"t": ts, "rss": {"wifi:ap1": -50.0}})
    half = len(steps) // 2
    cut = steps[half]["t"]
    for seq, (st, sc) in enumerate([(steps[:half], [s for s in scans if s["t"] < cut]),
                                    (steps[half:], [s for s in scans if s["t"] >= cut])]):
        answer = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": seq, "steps": st, "scans": sc})
        assert answer.status_code == 200, answer.text
    return sid, truth


def _mean_error(track: list[dict], truth: dict[float, tuple[float, float]]) -> float:
    return float(np.mean([math.dist((e["x"], e["y"]), truth[e["t"]]) for e in track]))


def test_the_smoothed_track_has_the_live_tracks_shape_and_is_no_worse(device, site, scripted):
    sid, truth = _walk(device, site, scripted)
    raw = device.get(f"/api/v1/sessions/{sid}/track")
    live = raw.json()
    # the default answer is byte for byte what it was before the extension
    before = [EstimateOut.model_validate(e).model_dump(mode="json") for e in live]
    assert raw.content == json.dumps(before, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode()
    assert device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "false"}).json() == live
    answer = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"})
    assert answer.status_code == 200, answer.text
    smoothed = answer.json()
    assert len(smoothed) == len(live) == 1 + N_STEPS + N_STEPS // SCAN_EVERY
    for key in ("t", "floor", "source"):
        assert [e[key] for e in smoothed] == [e[key] for e in live]
    # no refused fix on this walk: the live answer is as before the extension (no new key)
    assert all(set(e) == {"t", "x", "y", "floor", "building", "covariance", "source"} for e in live + smoothed)
    live_err, smooth_err = _mean_error(live, truth), _mean_error(smoothed, truth)
    print(f'mean error: live {live_err:.2f} m, smoothed {smooth_err:.2f} m')
    assert smooth_err <= live_err, (smooth_err, live_err)
    # smoothing uses later fixes too: the smoothed covariance is never wider than the live one
    for a, b in zip(live, smoothed, strict=True):
        assert np.trace(b["covariance"]) <= np.trace(a["covariance"]) + 1e-9


def test_the_smoothed_track_stays_in_the_floors_walkable_area(device, admin, scripted):
    """The walk's corridor (1 m wide along y = 2) as floor 0's walkable area: the kf tracker
    drifts out of it (kf knows no plan), but its live estimates are reported on the corridor's
    edge and the smoothed track is inside it throughout."""
    corridor = [[[0.0, 1.5], [50.0, 1.5], [50.0, 2.5], [0.0, 2.5]]]
    floors = [{**FLOORS[0], "walkable": corridor}, FLOORS[1]]
    answer = admin.post("/api/v1/sites", json={"name": "corridor", "floors": floors, "transmitters": TRANSMITTERS})
    assert answer.status_code == 201, answer.text
    sid, _ = _walk(device, answer.json()["id"], scripted)
    live = device.get(f"/api/v1/sessions/{sid}/track").json()
    smoothed = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"}).json()

    def inside(e: dict) -> bool:
        return -1e-9 <= e["x"] <= 50.0 + 1e-9 and 1.5 - 1e-9 <= e["y"] <= 2.5 + 1e-9

    assert all(inside(e) for e in live), [(e["x"], e["y"]) for e in live if not inside(e)][:5]
    assert any(abs(e["y"] - 1.5) < 1e-9 or abs(e["y"] - 2.5) < 1e-9 for e in live)  # moved to the edge
    assert all(inside(e) for e in smoothed), [(e["x"], e["y"]) for e in smoothed if not inside(e)][:5]


def test_a_closed_sessions_smoothed_track_can_be_read_and_others_cannot(device, admin, site, scripted):
    sid, _ = _walk(device, site, scripted)
    assert device.delete(f"/api/v1/sessions/{sid}").status_code == 204
    smoothed = device.get(f"/api/v1/sessions/{sid}/track?smoothed=true")
    assert smoothed.status_code == 200 and len(smoothed.json()) == 1 + N_STEPS + N_STEPS // SCAN_EVERY
    assert admin.get(f"/api/v1/sessions/{sid}/track?smoothed=true").json() == smoothed.json()
    assert device.get("/api/v1/sessions/nope/track?smoothed=true").status_code == 404
    assert device.get(f"/api/v1/sessions/{sid}/track?smoothed=maybe").status_code == 422


def test_a_refused_fix_is_marked_on_the_track(device, site, scripted):
    sid, _ = _walk(device, site, scripted, outlier_at=9)
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    marked = [i for i, e in enumerate(track) if "fix_refused" in e]
    scan_idx = [i for i, e in enumerate(track) if e["source"] == "scan"]
    assert marked == [scan_idx[9]] and track[marked[0]]["fix_refused"] is True
    smoothed = device.get(f"/api/v1/sessions/{sid}/track?smoothed=true").json()
    assert [i for i, e in enumerate(smoothed) if e.get("fix_refused")] == marked


def test_the_openapi_schema_documents_the_parameter_and_the_field(anonymous):
    schema = anonymous.get("/openapi.json").json()
    params = schema["paths"]["/api/v1/sessions/{session_id}/track"]["get"]["parameters"]
    smoothed = next(p for p in params if p["name"] == "smoothed")
    assert smoothed["in"] == "query" and "smoother" in smoothed["description"] and smoothed["schema"]["default"] is False
    assert "fix_refused" in schema["components"]["schemas"]["TrackEstimateOut"]["properties"]


@pytest.mark.parametrize("limit", [1, 4, 13])
def test_refused_fix_marks_survive_paging(device, site, scripted, limit):
    """A page reads the answers of its own batches only: the marks must be the whole track's."""
    sid, _ = _walk(device, site, scripted, outlier_at=9)
    track = device.get(f"/api/v1/sessions/{sid}/track").json()
    assert any("fix_refused" in e for e in track)
    got: list[dict] = []
    while True:
        answer = device.get(f"/api/v1/sessions/{sid}/track", params={"since": len(got) - 1, "limit": limit})
        assert answer.status_code == 200, answer.text
        got.extend(answer.json())
        if "link" not in answer.headers:
            break
    assert got == track
    # a page that starts at the marked estimate itself
    marked = next(i for i, e in enumerate(track) if "fix_refused" in e)
    page = device.get(f"/api/v1/sessions/{sid}/track", params={"since": marked - 1, "limit": 1}).json()
    assert page == [track[marked]] and page[0]["fix_refused"] is True


def _estimates(track: list[dict]) -> list[Estimate]:
    return [Estimate(e["t"], e["x"], e["y"], e["floor"], tuple(map(tuple, e["covariance"])), e["source"], e["building"])
            for e in track]


def test_a_self_calibrating_session_is_smoothed_over_its_whole_state(device, site, scripted, live_server):
    """ekf on the biased walk: the stored states make the smoother bend the path before the bias
    was learned as that bias — better than the live track and than smoothing the position alone
    (what a track stored without states gets: shown by removing them)."""
    sid, truth = _walk(device, site, scripted, filter="ekf")
    live = device.get(f"/api/v1/sessions/{sid}/track").json()
    smoothed = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"}).json()
    marginal = [e.to_dict() for e in smooth_track(_estimates(live))]
    live_err, full_err, marginal_err = (_mean_error(x, truth) for x in (live, smoothed, marginal))
    print(f"mean error: live {live_err:.2f}, position-only smoothing {marginal_err:.2f}, whole state {full_err:.2f} m")
    assert full_err < marginal_err < live_err
    with live_server.app.state.db.transaction() as s:
        s.execute(text("UPDATE track_estimates SET state = NULL WHERE session_id = :sid"), {"sid": sid})
    old = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"}).json()
    assert _same(old, marginal)


def test_a_particle_filter_sessions_steps_are_smoothed_through_its_clouds_own_moments(device, site, scripted,
                                                                                      live_server):
    """pf: every stored step estimate keeps its cloud's joint moments of the step (``"j"``) and the
    served smoothed track is the one smoothed through them, read back from the database; the same
    track stored without them (as before they were kept) is smoothed by the step's model: another
    answer, served at the Gaussian filters' scale."""
    sid, truth = _walk(device, site, scripted, filter="pf")
    with live_server.app.state.db.transaction() as s:
        rows = s.execute(select(TrackEstimate.idx, TrackEstimate.source, TrackEstimate.state)
                         .where(TrackEstimate.session_id == sid).order_by(TrackEstimate.idx)).all()
    assert all(("j" in r.state) == (r.source == "step") for r in rows)
    live = device.get(f"/api/v1/sessions/{sid}/track").json()
    smoothed = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"}).json()
    states = [FullState.from_dict(r.state) for r in rows]
    assert _same(smoothed, [e.to_dict() for e in smooth_track(_estimates(live), None, states)])
    with live_server.app.state.db.transaction() as s:
        for r in rows:
            s.execute(update(TrackEstimate).where(TrackEstimate.session_id == sid, TrackEstimate.idx == r.idx)
                      .values(state={k: v for k, v in r.state.items() if k != "j"}))
    model = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true"}).json()
    plain = [replace(f, joint=None) for f in states]
    assert _same(model, [e.to_dict() for e in smooth_track(_estimates(live), None, plain)])
    assert not _same(model, smoothed)
    print(f"mean error: live {_mean_error(live, truth):.2f}, smoothed by the cloud {_mean_error(smoothed, truth):.2f}, "
          f"by the model {_mean_error(model, truth):.2f} m")


def _same(a: list[dict], b: list[dict]) -> bool:
    return len(a) == len(b) and all(
        x["t"] == y["t"] and x["source"] == y["source"] and math.isclose(x["x"], y["x"], abs_tol=1e-9)
        and math.isclose(x["y"], y["y"], abs_tol=1e-9) for x, y in zip(a, b, strict=True))


def test_a_particle_filter_session_is_smoothed_by_its_particles(device, site, scripted, live_server):
    """pf with ``smoother=particles``: the session keeps its opening state and each batch's steps,
    scans and fixes, and the smoothed track replays them with the particle smoother — the live
    track's shape, better than it, and not the RTS's answer. A session whose kept inputs no longer
    reproduce its track (here: a fix changed in the database), or one stored before they were kept,
    gets a 409 that says so, while ``smoother=rts`` still smooths it."""
    sid, truth = _walk(device, site, scripted, filter="pf")
    url = f"/api/v1/sessions/{sid}/track"
    live = device.get(url).json()
    rts = device.get(url, params={"smoothed": "true"}).json()
    answer = device.get(url, params={"smoothed": "true", "smoother": "particles"})
    assert answer.status_code == 200, answer.text
    particles = answer.json()
    assert [(e["t"], e["source"], e["floor"]) for e in particles] == [(e["t"], e["source"], e["floor"]) for e in live]
    live_err, smooth_err = _mean_error(live, truth), _mean_error(particles, truth)
    print(f"mean error: live {live_err:.2f}, RTS {_mean_error(rts, truth):.2f}, particle-smoothed {smooth_err:.2f} m")
    assert smooth_err < live_err
    assert not _same(particles, rts)
    assert _same(device.get(url, params={"smoothed": "true", "smoother": "rts"}).json(), rts)
    db = live_server.app.state.db
    batches = SessionBatch.__table__
    with db.transaction() as s:
        kept = s.execute(select(batches.c.seq, batches.c.inputs).where(batches.c.session_id == sid)
                         .order_by(batches.c.seq)).all()
        assert [seq for seq, _ in kept] == [0, 1] and all(i is not None for _, i in kept)
        inputs = dict(kept[1][1])
        first = next(i for i, f in enumerate(inputs["fixes"]) if "x" in f)
        inputs["fixes"] = [*inputs["fixes"][:first], {**inputs["fixes"][first], "x": inputs["fixes"][first]["x"] + 5.0},
                           *inputs["fixes"][first + 1:]]
        s.execute(update(batches).where(batches.c.session_id == sid, batches.c.seq == 1).values(inputs=inputs))
    tampered = device.get(url, params={"smoothed": "true", "smoother": "particles"})
    assert tampered.status_code == 409, tampered.text
    assert "do not reproduce its track" in tampered.text and "smoother=rts" in tampered.text
    with db.transaction() as s:
        s.execute(update(TrackingSession.__table__).where(TrackingSession.id == sid).values(opening_state=None))
    assert device.get(url, params={"smoothed": "true", "smoother": "particles"}).status_code == 409
    assert _same(device.get(url, params={"smoothed": "true"}).json(), rts)


def test_only_a_particle_filter_session_keeps_its_inputs_and_has_particles_to_smooth(device, site, scripted,
                                                                                      live_server):
    sid, _ = _walk(device, site, scripted, filter="skpf")
    with live_server.app.state.db.transaction() as s:
        opening = s.execute(select(TrackingSession.opening_state).where(TrackingSession.id == sid)).scalar()
        inputs = s.execute(select(SessionBatch.inputs).where(SessionBatch.session_id == sid)).scalars().all()
    assert opening is None and inputs == [None, None]
    answer = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": "true", "smoother": "particles"})
    assert answer.status_code == 422 and "needs a particle-filter session" in answer.text and "skpf" in answer.text


@pytest.mark.parametrize("params", [{"smoother": "particles"}, {"smoothed": "true", "smoother": "ffbsm"},
                                    {"smoothed": "false", "smoother": "particles"}])
def test_a_smoother_that_does_not_apply_is_refused(device, site, scripted, params):
    sid, _ = _walk(device, site, scripted, filter="pf")
    answer = device.get(f"/api/v1/sessions/{sid}/track", params=params)
    assert answer.status_code == 422 and "smoother" in answer.text


def test_a_session_too_long_to_replay_is_refused_with_a_conflict(device, site, scripted, monkeypatch):
    sid, _ = _walk(device, site, scripted, filter="pf")  # two batches
    monkeypatch.setattr(sessions_service, "MAX_REPLAY_BATCHES", 1)
    url = f"/api/v1/sessions/{sid}/track"
    answer = device.get(url, params={"smoothed": "true", "smoother": "particles"})
    assert answer.status_code == 409 and "has 2 batches" in answer.text and "at most 1" in answer.text
    assert device.get(url, params={"smoothed": "true"}).status_code == 200


def test_a_particle_smoothed_track_read_again_is_not_replayed_again(device, site, live_server, monkeypatch):
    """One service per process (as the app holds it): a second read of the same session at the same
    seq and site revision answers from the cache; a new batch replays again."""
    fake = ScriptedPositioning()
    service = SessionService(live_server.app.state.db, fake)
    live_server.app.dependency_overrides[session_service] = lambda: service
    replays = []

    def counted(*args, **kwargs):
        replays.append(1)
        return smoothed_by_replay(*args, **kwargs)

    monkeypatch.setattr(sessions_service, "smoothed_by_replay", counted)
    try:
        sid, _ = _walk(device, site, fake, filter="pf")
        url, params = f"/api/v1/sessions/{sid}/track", {"smoothed": "true", "smoother": "particles"}
        first = device.get(url, params=params).json()
        assert device.get(url, params=params).json() == first and len(replays) == 1
        t = first[-1]["t"] + 0.5
        answer = device.post(f"/api/v1/sessions/{sid}/batches",
                             json={"seq": 2, "steps": [{"t": t, "length_m": 0.7, "heading_deg": 90.0}], "scans": []})
        assert answer.status_code == 200, answer.text
        third = device.get(url, params=params).json()
        assert len(third) == len(first) + 1 and len(replays) == 2
    finally:
        live_server.app.dependency_overrides.pop(session_service)
