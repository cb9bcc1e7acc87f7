"""The RTS smoother over a stored track: equal to filterpy's RTS smoother for the two-state
EKF, and better than the live track on a simulated walk."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from filterpy.kalman import KalmanFilter

from server.estimation.tracking import make_tracker
from server.estimation.tracking.motion import step_noise_cov
from server.estimation.tracking.smoother import smooth_track
from server.estimation.types import Estimate, Fix, Step, step_displacement
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
