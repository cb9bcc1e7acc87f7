"""The RTS smoother over a stored track: equal to filterpy's RTS smoother for the two-state
EKF, and better than the live track on a simulated walk."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from server.estimation.tracking import make_tracker
from server.estimation.tracking.motion import step_noise_cov
from server.estimation.tracking.smoother import ENSEMBLE_COV_SCALE, SMOOTHED_COV_SCALE, smooth_track
from server.estimation.types import Estimate, Fix, FullState, Step, StepJoint, step_displacement
from tests.helpers.simulate import simulate_walk


def _track(name: str, walk, floor_change_at: int | None = None):
    """The track as the server stores it, plus per time index the filtered state, Q and u."""
    t = make_tracker(name, walk.truth[0], np.eye(2) * 0.5, seed=1, **({"q": 0.01} if name != "kf" else {}))
    track = [Estimate.of(0.0, t.mean, t.covariance, 0, "init")]
    filtered, Qs, us = [(t.mean, t.covariance)], [np.zeros((2, 2))], [np.zeros(2)]
    k = 0
    for e in walk.events:
        floor = 1 if floor_change_at is not None and k >= floor_change_at else 0
        if isinstance(e, Step):
            k += 1
            t.predict(e)
            track.append(Estimate.of(e.t, t.mean, t.covariance, floor, "step"))
            filtered.append((t.mean, t.covariance))
            Qs.append(step_noise_cov(e) + 0.01 * np.eye(2))
            us.append(step_displacement(e.length_m, e.heading_deg))
        else:
            t.update(e)
            track.append(Estimate.of(float(k) + 0.5, t.mean, t.covariance, floor, "scan"))
            filtered[-1] = (t.mean, t.covariance)
    return track, filtered, Qs, us


def test_equals_filterpy_rts_for_the_two_state_ekf():
    walk = simulate_walk(seed=3, legs=((0.0, 15), (90.0, 15)))
    track, filtered, Qs, us = _track("ekf-xy", walk)
    # filterpy's smoother has no control input: take the known displacements out first.
    U = np.cumsum(us, axis=0)
    Xs = np.array([m for m, _ in filtered]) - U
    Ps = np.array([P for _, P in filtered])
    xs_ref, Ps_ref, _, _ = KalmanFilter(dim_x=2, dim_z=2).rts_smoother(Xs, Ps, Fs=[np.eye(2)] * len(Xs), Qs=Qs)
    smoothed = smooth_track(track)
    assert len(smoothed) == len(track)
    assert [(e.t, e.source, e.floor) for e in smoothed] == [(e.t, e.source, e.floor) for e in track]
    last_of_index = {}
    k = -1
    for i, e in enumerate(smoothed):
        k += e.source in ("init", "step")
        last_of_index[k] = i
    for k, i in last_of_index.items():
        np.testing.assert_allclose([smoothed[i].x, smoothed[i].y], xs_ref[k] + U[k], atol=1e-9)
        np.testing.assert_allclose(np.array(smoothed[i].covariance), Ps_ref[k], atol=1e-9)


def test_smoothing_beats_the_live_track_and_a_floor_change_splits_it():
    walk = simulate_walk(seed=4, legs=((0.0, 30), (90.0, 30)), fix_std_m=2.0)
    for name in ("ekf", "ekf-xy", "skpf", "kf"):
        track, *_ = _track(name, walk)
        smoothed = smooth_track(track)
        step_idx = [i for i, e in enumerate(track) if e.source == "step"]
        live = np.array([[track[i].x, track[i].y] for i in step_idx])
        smooth = np.array([[smoothed[i].x, smoothed[i].y] for i in step_idx])
        err_live = np.hypot(*(live - walk.truth[1:]).T).mean()
        err_smooth = np.hypot(*(smooth - walk.truth[1:]).T).mean()
        assert err_smooth < 0.97 * err_live, (name, err_smooth, err_live)
    track, *_ = _track("ekf-xy", walk, floor_change_at=30)
    smoothed = smooth_track(track)
    cut = next(i for i, e in enumerate(track) if e.floor == 1)
    # the last estimate before the change is its interval's end: the smoother leaves it as it was
    assert (smoothed[cut - 1].x, smoothed[cut - 1].y) == (track[cut - 1].x, track[cut - 1].y)
    assert smooth_track([]) == []


def test_a_building_change_at_the_same_level_splits_the_track_and_keeps_each_building():
    walk = simulate_walk(seed=4, legs=((0.0, 30), (90.0, 30)), fix_std_m=2.0)
    track, *_ = _track("ekf-xy", walk)
    cut = len(track) // 2
    track = [replace(e, building=1) if i >= cut else e for i, e in enumerate(track)]
    smoothed = smooth_track(track)
    assert [e.building for e in smoothed] == [e.building for e in track]
    assert (smoothed[cut - 1].x, smoothed[cut - 1].y) == (track[cut - 1].x, track[cut - 1].y)


def test_a_cloud_that_shrinks_in_a_step_does_not_blow_the_smoothed_track_up():
    """A PF's step can shrink its covariance (walls kill the particles on one side). Read as
    negative process noise, that would give an RTS gain above 1, amplifying backwards; the
    smoother drops the negative part, so no smoothed position leaves the filtered ones' span."""
    track = [Estimate.of(0.0, np.array([0.0, 0.0]), np.eye(2), 0, "init")]
    rng = np.random.default_rng(4)
    for k in range(1, 40):
        x = np.array([0.7 * k, 0.0]) + rng.normal(0.0, 0.3, 2)
        track.append(Estimate.of(float(k), x, np.eye(2) * 0.5, 0, "step"))  # shrank from 1.0
        track.append(Estimate.of(k + 0.5, x + rng.normal(0.0, 0.3, 2), np.eye(2), 0, "scan"))
    smoothed = smooth_track(track)
    xs = np.array([[e.x, e.y] for e in track])
    for e in smoothed:
        assert xs[:, 0].min() - 3.0 <= e.x <= xs[:, 0].max() + 3.0
        assert xs[:, 1].min() - 3.0 <= e.y <= xs[:, 1].max() + 3.0
        assert np.all(np.linalg.eigvalsh(np.array(e.covariance)) > 0)


def test_smoothed_positions_stay_in_the_floors_walkable_area_and_nothing_else_moves():
    """A corridor 1 m wide along y = 0 and fixes biased 1.5 m to its side: the plain smoother
    follows them out of the corridor; with the floor's walkable area every smoothed position
    is inside it, those the plain smoother left inside are unchanged, covariances too, and
    another floor's area changes nothing."""
    from server.estimation.floorplan import Walkable

    walk = simulate_walk(seed=4, legs=((90.0, 40),), fix_std_m=1.0)
    walk.events = [replace(e, y=e.y + 1.5) if isinstance(e, Fix) else e for e in walk.events]
    track, *_ = _track("ekf-xy", walk)
    corridor = Walkable([[[-5.0, -0.5], [40.0, -0.5], [40.0, 0.5], [-5.0, 0.5]]])
    plain = smooth_track(track)
    kept = smooth_track(track, {(0, 0): corridor})
    xy_plain = np.array([[e.x, e.y] for e in plain])
    xy_kept = np.array([[e.x, e.y] for e in kept])
    inside = corridor.contains(xy_plain)
    assert (~inside).sum() > len(track) // 4  # the bias took the plain smoother out
    assert corridor.contains(xy_kept).all()
    np.testing.assert_array_equal(xy_kept[inside], xy_plain[inside])
    assert [e.covariance for e in kept] == [e.covariance for e in plain]
    assert smooth_track(track, {(0, 1): corridor}) == plain


def _full_state_track(n: int = 12, seed: int = 4):
    """A synthetic stored track of a self-calibrating filter: per time index a step estimate
    carrying the predicted state x⁻ = F x (F the step's Jacobian at the filtered x, so the model is
    linear and filterpy's RTS is exact) and P⁻ = F P Fᵀ + Q, then a scan estimate with some
    filtered state; the first index is the initial estimate."""
    from server.estimation.tracking import selfcal

    rng = np.random.default_rng(seed)

    def spd(scale: float) -> np.ndarray:
        A = rng.normal(0, 1, (4, 4)) * scale
        return A @ A.T + np.diag([0.5, 0.5, 0.01, 0.001])

    xf = [np.array([0.0, 0.0, 0.1, 1.0])]
    Pf = [spd(0.2)]
    Fs, Qs, track, states = [np.eye(4)], [np.zeros((4, 4))], [], []
    track.append(Estimate.of(0.0, xf[0][:2], Pf[0][:2, :2], 0, "init"))
    states.append(FullState.of(xf[0], Pf[0]))
    for k in range(1, n):
        step = Step(float(k), 0.7 + 0.05 * rng.normal(), float(rng.uniform(0, 360)))
        F, _ = selfcal.jacobians(xf[-1], step.length_m, np.radians(step.heading_deg))
        Q = spd(0.1)
        xp, Pp = F @ xf[-1], F @ Pf[-1] @ F.T + Q
        track.append(Estimate.of(float(k), xp[:2], Pp[:2, :2], 0, "step"))
        states.append(FullState.of(xp, Pp, step))
        x, P = xp + rng.normal(0, 0.3, 4) * [1, 1, 0.05, 0.01], spd(0.15)  # some update's outcome
        track.append(Estimate.of(k + 0.5, x[:2], P[:2, :2], 0, "scan"))
        states.append(FullState.of(x, P))
        xf.append(x)
        Pf.append(P)
        Fs.append(F)
        Qs.append(Q)
    return track, states, np.array(xf), np.array(Pf), Fs, Qs


def test_the_full_state_smoother_equals_filterpy_rts_over_the_whole_state():
    track, states, xf, Pf, Fs, Qs = _full_state_track()
    xs_ref, Ps_ref, _, _ = KalmanFilter(dim_x=4, dim_z=2).rts_smoother(xf, Pf, Fs=Fs, Qs=Qs)
    smoothed = smooth_track(track, None, states)
    assert [(e.t, e.source) for e in smoothed] == [(e.t, e.source) for e in track]
    for k in range(len(xf)):
        for i in ([0] if k == 0 else [2 * k - 1, 2 * k]):  # every estimate of index k gets its smoothed state
            np.testing.assert_allclose([smoothed[i].x, smoothed[i].y], xs_ref[k][:2], atol=1e-8)
            # served ×SMOOTHED_COV_SCALE: the RTS covariance calibrated to the smoother's errors
            np.testing.assert_allclose(np.array(smoothed[i].covariance), SMOOTHED_COV_SCALE * Ps_ref[k][:2, :2],
                                       atol=1e-8)
    # the position marginal alone (what a track without states gets) is another answer
    marginal = smooth_track(track)
    assert max(abs(a.x - b.x) + abs(a.y - b.y) for a, b in zip(marginal, smoothed, strict=True)) > 1e-3


def test_a_step_as_a_cloud_saw_it_smooths_as_the_model_when_the_cloud_is_the_model():
    """The ensemble RTS (``StepJoint``: ancestors' moments and the cross-covariance) with the joint
    moments a linear-Gaussian step has (old state x, P; cross P Fᵀ; predicted F P Fᵀ + Q) is the
    RTS: equal to filterpy's over the whole state; a joint from elsewhere gives another answer, and
    a run with a step that lacks its joint is smoothed by the model there and served at its scale."""
    track, states, xf, Pf, Fs, Qs = _full_state_track()
    joined = [s if s.step is None else replace(s, joint=StepJoint(
        tuple(xf[k - 1]), tuple(map(tuple, Pf[k - 1])), tuple(map(tuple, Pf[k - 1] @ Fs[k].T))))
        for s, k in zip(states, [0] + [k for k in range(1, len(xf)) for _ in (0, 1)], strict=True)]
    xs_ref, Ps_ref, _, _ = KalmanFilter(dim_x=4, dim_z=2).rts_smoother(xf, Pf, Fs=Fs, Qs=Qs)
    smoothed = smooth_track(track, None, joined)
    for k in range(len(xf)):
        i = 0 if k == 0 else 2 * k
        np.testing.assert_allclose([smoothed[i].x, smoothed[i].y], xs_ref[k][:2], atol=1e-8)
        # (served at the cloud's own scale: a track whose every step carries its joint is a PF's)
        np.testing.assert_allclose(np.array(smoothed[i].covariance), ENSEMBLE_COV_SCALE * Ps_ref[k][:2, :2], atol=1e-8)
    assert all(FullState.from_dict(json.loads(json.dumps(s.to_dict()))) == s for s in joined)
    other = [s if s.joint is None else replace(s, joint=replace(s.joint, cross=tuple(
        map(tuple, 0.5 * np.array(s.joint.cross))))) for s in joined]
    assert max(abs(a.x - b.x) for a, b in zip(smooth_track(track, None, other), smoothed, strict=True)) > 1e-3
    mixed = list(joined)
    mixed[3] = replace(mixed[3], joint=None)  # (the step of index 2)
    for a, b in zip(smooth_track(track, None, mixed), smooth_track(track, None, states), strict=True):
        np.testing.assert_allclose([a.x, a.y, *np.ravel(a.covariance)], [b.x, b.y, *np.ravel(b.covariance)], atol=1e-8)


def test_a_particle_filter_keeps_its_steps_joint_moments_through_kills_and_a_replays_descent():
    """Without walls a PF's step pairs every particle with itself: the ancestors' moments are the
    cloud's before the step (to round-off), and the cross-covariance is the model's P Fᵀ (sampling
    error aside); with a wall that kills the particles that start west of it, the survivors' ancestors sit east and
    narrower; a replay's descent record goes on through the step as the joint saw it."""
    from server.estimation.tracking import selfcal
    from server.estimation.tracking.pf import weighted_covariance

    t = make_tracker("pf", [0.0, 0.0], np.eye(2), seed=3, n_particles=20000)
    before_m, before_P = t.state_mean, t.state_covariance
    step = Step(1.0, 0.7, 90.0, length_std_m=0.05, heading_std_deg=5.0)
    t.predict(step)
    j = t.step_joint
    np.testing.assert_allclose(j.origin_mean, before_m, atol=1e-12)
    np.testing.assert_allclose(np.array(j.origin_covariance), before_P, atol=1e-12)
    F, _ = selfcal.jacobians(before_m, step.length_m, np.radians(step.heading_deg))
    model = before_P @ F.T
    np.testing.assert_allclose(np.array(j.cross), model, atol=0.05 * np.abs(model).max())

    walled = make_tracker("pf", [0.0, 0.0], np.eye(2), walls=[[0.0, -10.0, 0.0, 10.0]], seed=3, n_particles=4000)
    start_m, start_P = walled.state_mean, walled.state_covariance
    walled.lineage = np.arange(4000)  # as a replay's particle smoother keeps it
    before = walled.particles[:, :4].copy()
    walled.predict(Step(1.0, 3.0, 90.0))  # 3 m east: those that start west of the wall within 3 m die
    j = walled.step_joint
    assert j.origin_mean[0] > start_m[0] + 0.5 and j.origin_covariance[0][0] < 0.6 * start_P[0, 0]
    assert walled.lineage is not None and walled.lineage.min() >= 0
    pairs = np.hstack((before[walled.lineage], walled.particles[:, :4]))
    assert j == StepJoint.of(walled.weights @ pairs[:, :4], weighted_covariance(pairs, walled.weights))


def test_a_heading_bias_stored_on_either_side_of_the_wrap_smooths_as_the_same_angle():
    """The trackers keep b in (−π, π]: a walk whose bias drifts past ±180° stores b jumping by 2π
    between estimates. The smoother must see the same angle (it once read the jump as a 360° error
    and bent a held-out walk's smoothed track 45 m off while the live one stayed within 2 m)."""
    track, states, *_ = _full_state_track(n=16)
    rng = np.random.default_rng(7)
    turns = rng.integers(-1, 2, len(states))
    assert len(set(turns.tolist())) == 3
    wrapped = [FullState.of(np.array(f.mean) + [0, 0, 2 * np.pi * m, 0], f.covariance,
                            None if f.step is None else Step(0.0, *f.step))
               for f, m in zip(states, turns, strict=True)]
    reference, smoothed = smooth_track(track, None, states), smooth_track(track, None, wrapped)
    for a, b in zip(reference, smoothed, strict=True):
        np.testing.assert_allclose([b.x, b.y], [a.x, a.y], atol=1e-8)
        np.testing.assert_allclose(np.array(b.covariance), np.array(a.covariance), atol=1e-8)


def test_a_run_with_an_estimate_without_its_state_is_smoothed_over_the_position():
    track, states, *_ = _full_state_track()
    states[5] = None  # e.g. stored before the states were
    assert smooth_track(track, None, states) == smooth_track(track)


def test_the_session_records_the_whole_state_of_a_self_calibrating_tracker_only():
    from server.estimation.session import SessionEstimator
    from server.estimation.types import SiteMap

    walk = simulate_walk(seed=2, legs=((0.0, 6),))
    steps = [e for e in walk.events if isinstance(e, Step)]
    for name, has in (("ekf", True), ("pf", True), ("kf", False), ("ekf-xy", False)):
        est = SessionEstimator(name, seed=1)
        est.start(walk.truth[0], None, 0, [], None, "init")
        out = est.apply_batch(steps, [], None, SiteMap())
        assert len(out.states) == len(out.estimates) == len(steps)
        if not has:
            assert all(s is None for s in out.states), name
            continue
        for e, s, step in zip(out.estimates, out.states, steps, strict=True):
            assert s is not None and s.step == (step.length_m, step.heading_deg)
            assert (e.x, e.y) == pytest.approx(s.mean[:2]) and np.array(e.covariance) == pytest.approx(
                np.array(s.covariance)[:2, :2])
            assert type(s).from_dict(json.loads(json.dumps(s.to_dict()))) == s  # stored and read back exactly
            assert (s.joint is not None) == (name == "pf")  # a cloud's own step moments: the PF's only


@pytest.mark.parametrize("seed", range(6))
def test_smoothed_covariances_stay_positive_definite_after_a_collapsed_cloud(seed):
    """A PF cloud collapsed onto a few copies (walls killed the rest) has a near-singular
    covariance; the recursion's round-off must not serve a smoothed covariance with a negative
    variance (a NEES below 0)."""
    rng = np.random.default_rng(seed)
    n = 60
    track, states = [], []
    x = np.array([0.0, 0.0, 0.0, 1.0])
    for k in range(n):
        a = rng.normal(0, 1, (4, 1)) * 10.0 ** rng.uniform(-1, 1)
        P = a @ a.T + 1e-13 * np.eye(4)  # rank one: the cloud's copies of one particle
        step = None if k == 0 else Step(float(k), 0.7, float(rng.uniform(0, 360)))
        x = x + rng.normal(0, 0.5, 4) * [1, 1, 0.02, 0.01]
        track.append(Estimate.of(float(k), x[:2], P[:2, :2] + 1e-9 * np.eye(2), 0, "init" if k == 0 else "step"))
        states.append(FullState.of(x, P, step))
    smoothed = smooth_track(track, None, states)
    for e in smoothed:
        assert np.linalg.eigvalsh(np.array(e.covariance))[0] > 0
