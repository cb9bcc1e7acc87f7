"""Particle filter: walls kill particles, likelihood weighting, resampling equals filterpy."""

import math

import numpy as np
import pytest
from filterpy.monte_carlo import systematic_resample as filterpy_systematic_resample

from server.estimation.tracking import make_tracker
from server.estimation.tracking.geometry import crosses_walls
from server.estimation.tracking.resampling import effective_sample_size, systematic_resample
from server.estimation.types import Fix, Step

WALL = [[-10.0, 1.0, 10.0, 1.0]]  # an east-west wall 1 m north of the start


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_systematic_resample_equals_filterpy_for_same_offset(seed):
    rng = np.random.default_rng(seed)
    w = rng.random(500) ** 4
    w /= w.sum()
    np.random.seed(seed)
    expected = filterpy_systematic_resample(w)
    np.random.seed(seed)
    u = np.random.random()
    np.testing.assert_array_equal(systematic_resample(w, u), expected)


def test_crosses_walls_geometry():
    walls = np.array(WALL)
    start = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [11.0, 0.0]])
    end = np.array([[0.0, 2.0], [0.0, 0.9], [5.0, 0.5], [11.0, 2.0]])
    np.testing.assert_array_equal(crosses_walls(start, end, walls), [True, False, False, False])


def test_pf_particles_never_end_beyond_a_wall():
    t = make_tracker("pf-xy", [0, 0], np.eye(2) * 0.05, walls=WALL, seed=7)
    assert t.params["n_particles"] == 1000
    for k in range(6):
        t.predict(Step(k, 0.4, 0.0))  # walking north into the wall
        assert np.all(t.particles[:, 1] < 1.0)
    assert t.mean[1] < 1.0
    # without the wall the same walk goes through it
    free = make_tracker("pf-xy", [0, 0], np.eye(2) * 0.05, seed=7)
    for k in range(6):
        free.predict(Step(k, 0.4, 0.0))
    assert free.mean[1] > 2.0


def test_pf_keeps_track_when_every_particle_would_die():
    t = make_tracker("pf-xy", [0, 0.9], np.eye(2) * 1e-4, walls=WALL, seed=1, q=0.0)
    t.predict(Step(0, 1.0, 0.0, length_std_m=0.0, heading_std_deg=0.0))
    np.testing.assert_allclose(t.mean, [0.0, 1.9], atol=0.05)


def test_pf_update_weights_are_gaussian_likelihood():
    t = make_tracker("pf-xy", [0, 0], np.eye(2), seed=3, resample_threshold=0.0)
    before = t.particles.copy()
    R = np.diag([2.0, 0.5])
    t.update(Fix(1.0, -0.5, 0, R))
    d = before - np.array([1.0, -0.5])
    lik = np.exp(-0.5 * (d[:, 0] ** 2 / 2.0 + d[:, 1] ** 2 / 0.5))
    # weights are kept as stored: a byte each, their ratio to the largest within ±2.2 %
    # (then normalised), 0 below 2^-15.9 of it
    exact = lik / lik.sum()
    kept = lik / lik.max() > 2.0**-15.9
    np.testing.assert_allclose(t.weights[kept], exact[kept], rtol=0.045)
    assert np.all(t.weights[~kept] == 0.0)
    np.testing.assert_allclose(t.mean, exact @ before, atol=0.01)


def test_pf_resamples_when_degenerate():
    t = make_tracker("pf-xy", [0, 0], np.eye(2), seed=3)
    t.update(Fix(1.0, 0.0, 0, np.eye(2) * 0.01))
    np.testing.assert_allclose(t.weights, np.float32(1.0 / len(t.weights)))
    # exact posterior mean: 1·1/(1 + 0.01) ≈ 0.99
    assert abs(t.mean[0] - 0.99) < 0.1
    assert len(np.unique(t.particles[:, 0])) < 200  # collapsed onto the few likely ones


def test_pf_range_update_gated_and_wall_side():
    t = make_tracker("pf-xy", [0, 0.5], np.eye(2), seed=4)
    assert t.update_range([0, 0], 3.5, 0.5) is False
    assert t.update_range([0, 0], 0.5, 0.2, on_wall=[-5, 0, 5, 0]) is True
    assert np.all(t.particles[np.abs(t.particles[:, 0]) <= 5, 1] > 0)


def test_pf_range_likelihood_is_log_normal():
    # A range r ± σr weighs a particle at distance d by exp(−½ (ln d − ln r)² / (σr/r)²).
    t = make_tracker("pf-xy", [1.0, 0.5], np.eye(2), seed=5, resample_threshold=0.0)
    before = t.particles.copy()
    assert t.update_range([0.0, 0.0], 1.2, 0.4) is True
    d = np.hypot(before[:, 0], before[:, 1])
    lik = np.exp(-0.5 * ((np.log(np.maximum(d, 0.1)) - math.log(1.2)) / (0.4 / 1.2)) ** 2)
    exact = lik / lik.sum()
    kept = lik / lik.max() > 2.0**-15.9  # the stored weights' resolution (see the Gaussian test above)
    np.testing.assert_allclose(t.weights[kept], exact[kept], rtol=0.045)
    np.testing.assert_allclose(t.mean, exact @ before, atol=0.01)


def test_pf_strong_reading_of_a_far_beacon_does_not_collapse_the_cloud():
    # The cloud is 10 m from a beacon heard as if 2.4 ± 1 m away (shadowing). In range space that
    # is a 7σ reading that left ~1 particle of 1,000 alive; in dB (log-range) it is ~3σ and the
    # whole cloud is nearly equally unlikely, so it keeps its spread.
    t = make_tracker("pf-xy", [10.0, 0.0], np.eye(2), seed=6, resample_threshold=0.0)
    spread = np.trace(t.covariance)
    t.update_range([0.0, 0.0], 2.4, 1.0)
    assert effective_sample_size(t.weights) > 300
    t2 = make_tracker("pf-xy", [10.0, 0.0], np.eye(2), seed=6)
    t2.update_range([0.0, 0.0], 2.4, 1.0)
    assert np.trace(t2.covariance) > 0.5 * spread
    assert np.hypot(*t2.mean) > 8.0  # pulled a little towards the beacon, not onto it


# -- floor plans: walkable space ---------------------------------------------------------------
# A 40 × 10 m floor whose north half between x = 10 and 30 is a closed room (an obstacle: no door),
# so the corridor along y ≈ 2 is the only way east.
CORRIDOR_PLAN = {"type": "FeatureCollection", "features": [
    {"type": "Feature", "properties": {"type": "floor"},
     "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [40, 0], [40, 10], [0, 10], [0, 0]]]}},
    {"type": "Feature", "properties": {},
     "geometry": {"type": "Polygon", "coordinates": [[[10, 5], [30, 5], [30, 10], [10, 10], [10, 5]]]}}]}


def _corridor():
    from server.estimation.floorplan import Transform, Walkable, read_plan

    plan = read_plan(CORRIDOR_PLAN, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))))
    return plan, Walkable(plan.walkable)


@pytest.mark.parametrize("name", ["pf", "pf-xy"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_pf_with_the_plan_never_ends_in_the_room_it_cannot_reach(name, seed):
    """East along the corridor with a PDR heading biased 14° north: dead reckoning (and the PF
    without the plan) ends inside the room; with the plan no particle is ever in it."""
    plan, area = _corridor()
    walk = [Step(k, 0.7, 90.0 - 14.0, length_std_m=0.1, heading_std_deg=3.0) for k in range(40)]  # 28 m east
    room = np.array([[10.0, 5.0], [30.0, 10.0]])

    def in_room(p):
        return (p[..., 0] > room[0, 0]) & (p[..., 0] < room[1, 0]) & (p[..., 1] > room[0, 1])

    free = make_tracker(name, [2.0, 2.0], np.eye(2) * 0.05, seed=seed)
    for s in walk:
        free.predict(s)
    assert in_room(free.mean)  # the test's walk does reach the room without a plan

    t = make_tracker(name, [2.0, 2.0], np.eye(2) * 0.05, walls=plan.walls, seed=seed)
    t.set_walkable(area)
    for s in walk:
        t.predict(s)
        assert not in_room(t.particles[:, :2]).any()
        assert area.contains(t.particles[:, :2]).all()
    # the mean of a cloud that rounds the room's corner may sit on its wall, not inside it
    assert not in_room(t.mean - np.array([0.0, 0.5])) and t.mean[0] > 20.0


def test_pf_redraws_around_the_last_estimate_when_every_particle_would_die():
    """Walking into the end of a dead end: every particle would leave walkable space; the cloud is
    redrawn around the estimate before the step, inside walkable space only."""
    from server.estimation.floorplan import Walkable

    area = Walkable([[[0, 0], [10, 0], [10, 2], [0, 2], [0, 0]]])
    t = make_tracker("pf", [9.5, 1.0], np.eye(2) * 0.01, seed=5, q=0.0)
    t.set_walkable(area)
    before = t.mean.copy()
    t.predict(Step(0, 2.0, 90.0, length_std_m=0.0, heading_std_deg=0.0))  # 2 m east: beyond x = 10
    assert area.contains(t.particles[:, :2]).all()
    assert np.linalg.norm(t.mean - before) < 2.0  # within a step of where it was
    np.testing.assert_allclose(t.weights, 1e-3)
    assert t.particles.shape == (1000, 4)


def test_pf_particle_count_follows_the_spread_of_the_cloud():
    """KLD-sampling: a fix that collapses the cloud leaves fewer particles; a wide cloud keeps
    the maximum; the count stays within [min_particles, n_particles]."""
    t = make_tracker("pf", [0, 0], np.eye(2) * 0.25, seed=3, min_particles=100)
    t.update(Fix(0.2, 0.0, 0, np.eye(2) * 0.05))
    tight = len(t.particles)
    assert t.params["min_particles"] <= tight < t.params["n_particles"]
    wide = make_tracker("pf", [0, 0], np.eye(2) * 400.0, seed=3, min_particles=100)
    wide.update(Fix(0.0, 0.0, 0, np.eye(2) * 300.0))
    wide._resample()
    assert len(wide.particles) == wide.params["n_particles"]
    for _ in range(5):  # the count can grow back as the cloud spreads again
        t.inflate(4.0)
        t._resample()
    assert len(t.particles) > tight


def test_pf_fixed_count_when_min_equals_max():
    t = make_tracker("pf-xy", [0, 0], np.eye(2), seed=3, n_particles=300, min_particles=300)
    t.update(Fix(1.0, 0.0, 0, np.eye(2) * 0.01))
    assert len(t.particles) == 300
    default = make_tracker("pf", [0, 0], np.eye(2), seed=3)  # KLD-sampling is off by default
    default.update(Fix(1.0, 0.0, 0, np.eye(2) * 0.01))
    assert len(default.particles) == default.params["n_particles"] == 1000


@pytest.mark.parametrize("name", ["pf", "pf-xy"])
def test_pf_state_is_packed_and_restores_exactly(name):
    import json

    from server.estimation.tracking import tracker_from_dict

    t = make_tracker(name, [3.0, 4.0], np.eye(2), seed=5)
    t.predict(Step(1.0, 0.7, 45.0))
    t.update(Fix(3.5, 4.5, 0, np.eye(2) * 2.0))
    data = json.loads(json.dumps(t.to_dict()))
    assert isinstance(data["state"]["particles"], dict)  # packed, not a list of numbers
    back = tracker_from_dict(data)
    np.testing.assert_array_equal(back.particles, t.particles)
    np.testing.assert_array_equal(back.weights, t.weights)
    for tr in (t, back):
        tr.predict(Step(2.0, 0.7, 90.0))
    np.testing.assert_array_equal(back.particles, t.particles)


def test_pf_state_stored_as_lists_still_loads():
    """States stored before packing hold plain lists of numbers (and 1,000 particles)."""
    from server.estimation.tracking import tracker_from_dict

    t = make_tracker("pf-xy", [0.0, 0.0], np.eye(2), seed=5)
    data = t.to_dict()
    data["state"]["particles"] = t.particles.tolist()
    data["state"]["weights"] = t.weights.tolist()
    back = tracker_from_dict(data)
    np.testing.assert_allclose(back.particles, t.particles, rtol=1e-6)  # kept as float32 values
    np.testing.assert_allclose(back.mean, t.mean, rtol=1e-6)


def test_particles_far_from_the_origin_keep_the_resolution_of_their_spread():
    """A byte per number on a grid spanning the cloud: a cloud 5 km from the site origin keeps
    its spread / 510 (float16 values would be metres off), and the stored particles take
    ≈ 1.25 characters each (base85)."""
    import json

    from server.estimation.tracking import tracker_from_dict

    raw = 5000.0 + 2.0 * np.random.default_rng(0).standard_normal(1000)
    u = make_tracker("pf", [0.0, 0.0], np.eye(2), seed=1)
    rounded = u._round(np.column_stack([raw, raw, np.zeros(1000), np.ones(1000)]), refit=True)
    assert np.abs(rounded[:, 0] - raw).max() <= 0.5 * np.ptp(raw) / 255 + 1e-9  # ≈ 2.6 cm
    t = make_tracker("pf", [5000.0, -3000.0], np.eye(2) * 4.0, seed=2)
    packed = json.dumps(t.to_dict()["state"]["particles"])
    assert len(packed) < 1000 * 4 * 1.35
    back = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    np.testing.assert_array_equal(back.particles, t.particles)


@pytest.mark.parametrize("name", ["pf", "pf-xy"])
def test_pf_with_resample_kills_off_keeps_the_survivors_weights_until_degenerate(name):
    """resample_kills=0: a wall kill zeroes the dead particles' weights and resamples only when
    the effective count drops below resample_threshold (as a fix does); the state with its
    zero weights restores exactly."""
    import json

    from server.estimation.tracking import tracker_from_dict

    t = make_tracker(name, [0, 0.3], np.eye(2) * 0.04, walls=WALL, seed=7, resample_kills=0)
    t.predict(Step(0, 0.45, 0.0))  # part of the cloud reaches the wall at y = 1
    dead = t.weights == 0
    assert 0 < dead.sum() < len(t.weights) / 2  # killed, not resampled: the dead rows stay, weightless
    assert np.all(t.particles[~dead, 1] < 1.0)
    assert effective_sample_size(t.weights) >= t.params["resample_threshold"] * len(t.weights)
    np.testing.assert_allclose(t.mean, t.weights @ t.particles[:, :2])
    assert t.mean[1] < 1.0
    back = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    np.testing.assert_array_equal(back.weights, t.weights)
    for tr in (t, back):
        tr.predict(Step(1, 0.45, 0.0))
    np.testing.assert_array_equal(back.particles, t.particles)
    np.testing.assert_array_equal(back.weights, t.weights)
    # the default resamples at the first kill: every weight equal
    d = make_tracker(name, [0, 0.3], np.eye(2) * 0.04, walls=WALL, seed=7)
    d.predict(Step(0, 0.45, 0.0))
    assert np.all(d.weights == d.weights[0])


def test_pf_with_resample_kills_off_resamples_when_most_die():
    t = make_tracker("pf-xy", [0, 0.5], np.eye(2) * 0.01, walls=WALL, seed=7, resample_kills=0)
    assert np.all(t.particles[:, 1] < 1.0)
    t.predict(Step(0, 0.7, 0.0))  # most of the cloud crosses y = 1
    assert np.all(t.weights == t.weights[0])  # resampled among the survivors
    assert np.all(t.particles[:, 1] < 1.0)


# -- the fixes' shared error (fix_bias_share) -------------------------------------------------
CORRIDOR = [[-5.0, -1.0, 80.0, -1.0], [-5.0, 1.0, 80.0, 1.0], [-5.0, -1.0, -5.0, 1.0], [80.0, -1.0, 80.0, 1.0]]


def _corridor_walk(share: float, seed: int, bias: tuple[float, float]) -> float:
    """Mean error of a pf walking 56 m east along a 2 m corridor (its plan given), steps of the
    right length, fixes every second step at the truth + ``bias`` + N(0, 1.5²), R = 16·I."""
    t = make_tracker("pf", [0, 0], np.eye(2) * 0.1, walls=CORRIDOR, seed=seed, fix_bias_share=share)
    rng = np.random.default_rng(100 + seed)
    errs, x = [], 0.0
    for k in range(80):
        x += 0.7
        t.predict(Step(k, 0.7, 90.0 + rng.normal(0, 2)))
        if k % 2 == 1:
            z = np.array([x, 0.0]) + bias + rng.normal(0, 1.5, 2)
            t.update(Fix(float(z[0]), float(z[1]), 0, np.eye(2) * 16.0))
        errs.append(np.hypot(t.mean[0] - x, t.mean[1]))
    return float(np.mean(errs))


def test_pf_with_a_plan_is_not_dragged_by_fixes_biased_together():
    """Fixes 5 m ahead all along the walk: fused as independent they pull the cloud forward (the
    step scale learns to run ahead); with a share of their error shared along the walk the cloud
    keeps to the steps. Unbiased fixes cost the shared error little."""
    biased = {share: np.mean([_corridor_walk(share, s, (5.0, 0.0)) for s in range(3)]) for share in (0.0, 0.3)}
    assert biased[0.3] < 0.6 * biased[0.0]
    honest = {share: np.mean([_corridor_walk(share, s, (0.0, 0.0)) for s in range(3)]) for share in (0.0, 0.3)}
    assert honest[0.3] < 1.5 * honest[0.0] + 0.1


@pytest.mark.parametrize(("walls", "shared"), [(CORRIDOR, True), (None, True), (CORRIDOR, False)])
def test_pf_fix_likelihood_with_the_shared_error_is_hand_computed(walls, shared):
    """With a plan a fix weighs as N(z; p + √ρ·L·u, (1 − ρ)·R), L Lᵀ = R; without one, or for a fix
    that does not share the walk's error (a landmark snap), as N(z; p, R)."""
    rho = 0.3
    t = make_tracker("pf", [10.0, 0.0], np.diag([4.0, 0.2]), walls=walls, seed=4, fix_bias_share=rho,
                     resample_threshold=0.0)
    assert t.particles.shape == (1000, 6)
    before = t.particles.copy()
    R = np.array([[9.0, 1.0], [1.0, 4.0]])
    z = np.array([11.0, 0.3])
    t.update(Fix(float(z[0]), float(z[1]), 0, R, shared_share=None if shared else 0.0))
    if walls is None or not shared:
        d, S = before[:, :2] - z, R
    else:
        d, S = before[:, :2] + np.sqrt(rho) * before[:, 4:6] @ np.linalg.cholesky(R).T - z, (1 - rho) * R
    lik = np.exp(-0.5 * np.einsum("ij,jk,ik->i", d, np.linalg.inv(S), d))
    exact = lik / lik.sum()
    kept = lik / lik.max() > 2.0**-15.9
    np.testing.assert_allclose(t.weights[kept], exact[kept], rtol=0.045)
    np.testing.assert_allclose(t.mean, exact @ before[:, :2], atol=0.01)


def test_pf_with_the_shared_error_restores_exactly():
    import json

    from server.estimation.tracking import tracker_from_dict

    t = make_tracker("pf", [0.0, 0.0], np.eye(2), walls=CORRIDOR, seed=5, fix_bias_share=0.3)
    t.predict(Step(1.0, 0.7, 90.0))
    t.update(Fix(1.5, 0.2, 0, np.eye(2) * 4.0))
    data = json.loads(json.dumps(t.to_dict()))
    assert len(json.dumps(data["state"]["particles"])) < 7800  # 6,000 codes and the grid
    back = tracker_from_dict(data)
    np.testing.assert_array_equal(back.particles, t.particles)
    for tr in (t, back):
        tr.predict(Step(2.0, 0.7, 90.0))
        tr.update(Fix(2.0, 0.0, 0, np.eye(2) * 4.0))
    np.testing.assert_array_equal(back.particles, t.particles)
    np.testing.assert_array_equal(back.weights, t.weights)


def test_pf_state_stored_before_the_shared_error_goes_on_without_it():
    """A pf stored with four columns (and no fix_bias_* parameters) loads as it was written:
    ρ = 0, the same particles, the same future."""
    from server.estimation.tracking import tracker_from_dict

    t = make_tracker("pf", [0.0, 0.0], np.eye(2), walls=CORRIDOR, seed=5, fix_bias_share=0.0)
    t.predict(Step(1.0, 0.7, 90.0))
    data = t.to_dict()
    del data["state"]["dim"]
    for k in ("fix_bias_share", "fix_bias_steps"):
        del data["params"][k]
    back = tracker_from_dict(data)
    assert back.params["fix_bias_share"] == 0.0 and back.particles.shape == (1000, 4)
    for tr in (t, back):
        tr.predict(Step(2.0, 0.7, 90.0))
        tr.update(Fix(1.5, 0.0, 0, np.eye(2) * 4.0))
    np.testing.assert_array_equal(back.particles, t.particles)
    assert tracker_from_dict(back.to_dict()).particles.shape == (1000, 4)


# -- the fixes' shared error learned per session (fix_bias_switch) ------------------------------
WIDE_CORRIDOR = [[-50.0, -5.0, 500.0, -5.0], [-50.0, 5.0, 500.0, 5.0]]


def _learned_share(seed: int, correlation: float) -> float:
    """The learned share, averaged over the last 200 of 300 steps east along a 10 m corridor, the
    compass 2° off, a fix every third step with errors of σ 3 m: independent ones (``correlation``
    0) or a Gauss–Markov error that the walk's fixes share (per fix ``correlation``)."""
    t = make_tracker("pf", [0, 0], np.eye(2), walls=WIDE_CORRIDOR, seed=seed, fix_bias_share=0.35,
                     fix_bias_switch=0.01)
    rng = np.random.default_rng(seed)
    bias, learned = np.zeros(2), []
    for k in range(300):
        t.predict(Step(k * 0.5, 0.7, 92.0))
        if k % 3 == 0:
            bias = correlation * bias + math.sqrt(1 - correlation**2) * rng.normal(0, 3, 2)
            z = np.array([0.7 * (k + 1), 0.0]) + bias
            t.update(Fix(float(z[0]), float(z[1]), 0, np.eye(2) * 9.0))
        learned.append(t.fix_bias_learned)
    return float(np.mean(learned[100:]))


def test_pf_learns_whether_its_fixes_share_an_error():
    """Half the particles start on each hypothesis (learned share ρ/2 = 0.175); independent fixes
    take it below that, fixes biased together near ρ (the flips keep it from reaching either end)."""
    independent = np.mean([_learned_share(s, 0.0) for s in range(3)])
    together = np.mean([_learned_share(s, 0.95) for s in range(3)])
    assert independent < 0.16 and together > 0.28


def test_pf_fix_likelihood_with_the_learned_share_is_hand_computed():
    """A particle on hypothesis k weighs a fix as N(z; p + √(ρk)·L·u, (1 − ρk)·R)."""
    rho = 0.4
    t = make_tracker("pf", [10.0, 0.0], np.diag([4.0, 0.2]), walls=CORRIDOR, seed=4, fix_bias_share=rho,
                     fix_bias_switch=0.01, resample_threshold=0.0)
    assert t.particles.shape == (1000, 7) and set(t.particles[:, 6]) == {0.0, 1.0}
    assert t.fix_bias_learned == pytest.approx(rho / 2)
    before = t.particles.copy()
    R = np.array([[9.0, 1.0], [1.0, 4.0]])
    z = np.array([11.0, 0.3])
    t.update(Fix(float(z[0]), float(z[1]), 0, R))
    share = rho * before[:, 6]
    d = before[:, :2] + np.sqrt(share)[:, None] * (before[:, 4:6] @ np.linalg.cholesky(R).T) - z
    lik = np.exp(-0.5 * np.einsum("ij,jk,ik->i", d, np.linalg.inv(R), d) / (1 - share)) / (1 - share)
    exact = lik / lik.sum()
    kept = lik / lik.max() > 2.0**-15.9
    np.testing.assert_allclose(t.weights[kept], exact[kept], rtol=0.045)
    np.testing.assert_allclose(t.fix_bias_learned, rho * (exact @ before[:, 6]), atol=0.005)


def test_pf_with_the_learned_share_restores_exactly_and_a_fixed_share_state_loads():
    """Seven columns survive a restore exactly; a state stored with a fixed share (six columns)
    loads under parameters that ask for the learned one and goes on with the fixed share."""
    from server.estimation.tracking import tracker_from_dict

    t = make_tracker("pf", [0.0, 0.0], np.eye(2), walls=CORRIDOR, seed=5, fix_bias_share=0.3, fix_bias_switch=0.05)
    for tr_steps in range(3):
        t.predict(Step(tr_steps, 0.7, 90.0))
    t.update(Fix(1.5, 0.2, 0, np.eye(2) * 4.0))
    back = tracker_from_dict(t.to_dict())
    fixed = make_tracker("pf", [0.0, 0.0], np.eye(2), walls=CORRIDOR, seed=5, fix_bias_share=0.3)
    fixed.predict(Step(1.0, 0.7, 90.0))
    data = fixed.to_dict()
    data["params"]["fix_bias_switch"] = 0.05
    old = tracker_from_dict(data)
    assert old.particles.shape == (1000, 6) and old.params["fix_bias_switch"] == 0.0 and old.fix_bias_learned is None
    for a, b in ((t, back), (fixed, old)):
        for tr in (a, b):
            tr.predict(Step(5.0, 0.7, 90.0))
            tr.update(Fix(2.0, 0.0, 0, np.eye(2) * 4.0))
        np.testing.assert_array_equal(b.particles, a.particles)
        np.testing.assert_array_equal(b.weights, a.weights)


# -- the cloud kept as wide as a Kalman update (kalman_floor) -----------------------------------
def _far_fix(kappa: float, seed: int, walls=None):
    """A pf (no resampling) from N(0, 4·I) given a fix at (6, 0) with R = I: the Bayesian posterior
    is N((4.8, 0), 0.8·I), but only the ~1 % of particles 2.4σ out carry its weight."""
    t = make_tracker("pf", [0.0, 0.0], np.eye(2) * 4.0, walls=walls, seed=seed, kalman_floor=kappa,
                     resample_threshold=0.0)
    before = t.particles.copy()
    t.update(Fix(6.0, 0.0, 0, np.eye(2)))
    return t, before


def test_pf_kalman_floor_keeps_the_cloud_as_wide_as_a_kalman_update():
    """The Kalman update of the cloud's own moments leaves P − P (P + R)⁻¹ P ≈ 0.8·I; the
    reweighted (and resampled) cloud alone is narrower than that on most draws, never with the floor."""
    narrower = 0
    for seed in range(6):
        out = {}
        for kappa in (0.0, 1.0):
            t = make_tracker("pf", [0.0, 0.0], np.eye(2) * 4.0, seed=seed, kalman_floor=kappa)
            P = t.covariance
            floor = P - P @ np.linalg.inv(P + np.eye(2)) @ P
            t.update(Fix(6.0, 0.0, 0, np.eye(2)))
            out[kappa] = np.linalg.eigvalsh(t.covariance)[0] / np.linalg.eigvalsh(floor)[0]
        narrower += out[0.0] < 0.9
        assert out[1.0] > 0.95
        np.testing.assert_allclose(t.mean, [4.7, 0.0], atol=0.35)
    assert narrower >= 4


def test_pf_kalman_floor_adds_no_calibration_spread_for_a_fix_that_agrees():
    t = make_tracker("pf", [0.0, 0.0], np.eye(2) * 4.0, seed=3, kalman_floor=1.0, resample_threshold=0.0)
    before, grid = t.particles.copy(), t._grid
    t.update(Fix(float(t.mean[0]), float(t.mean[1]), 0, np.eye(2) * 0.5))  # d² = 0: γ = 0
    np.testing.assert_array_equal(t.particles[:, 2:], before[:, 2:])
    for new, old in zip(t._grid, grid, strict=True):  # the unmoved columns keep their grid (not refitted)
        np.testing.assert_array_equal(new[2:], old[2:])
        assert not np.array_equal(new[:2], old[:2])
    assert not np.array_equal(t.particles[:, :2], before[:, :2])  # the positions' shortfall was made up
    far, before = _far_fix(1.0, 3)  # d² = 7.2: γ = 0.78
    assert np.std(far.particles[:, 2] - before[:, 2]) > 0


def test_pf_kalman_floor_keeps_a_strong_beacon_range_from_leaving_one_particle():
    """A beacon 10 m from the cloud's centre heard at 1 ± 0.3 m: reweighted alone, the handful of
    particles nearest it carry everything; kept as wide as the (linearised, log-range) Kalman update,
    the cloud keeps most of its spread across the range's direction."""
    spreads = {}
    for kappa in (0.0, 1.0):
        t = make_tracker("pf", [10.0, 0.0], np.eye(2) * 4.0, seed=2, kalman_floor=kappa)
        assert t.update_range([0.0, 0.0], 1.0, 0.3)
        spreads[kappa] = np.trace(t.covariance)
    assert spreads[1.0] > 4 * spreads[0.0]


def test_pf_kalman_floor_is_off_where_the_floor_has_a_plan():
    plain, _ = _far_fix(0.0, 1, walls=CORRIDOR)
    kept, _ = _far_fix(1.0, 1, walls=CORRIDOR)
    np.testing.assert_array_equal(kept.particles, plain.particles)


def test_pf_with_the_kalman_floor_restores_exactly():
    import json

    from server.estimation.tracking import tracker_from_dict

    t, _ = _far_fix(0.5, 7)
    back = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    for tr in (t, back):
        tr.predict(Step(2.0, 0.7, 90.0))
        tr.update(Fix(8.0, 1.0, 0, np.eye(2) * 2.0))
        tr.update_range([9.0, 3.0], 2.0, 0.6)
    np.testing.assert_array_equal(back.particles, t.particles)
    np.testing.assert_array_equal(back.weights, t.weights)


# -- a step that leaves a few survivors ----------------------------------------------------------
# A wall along x = 5 with a 4 mm door at y = 0: a cloud walking east through it keeps a few particles.
DOOR_WALLS = [[5.0, -10.0, 5.0, 0.0], [5.0, 0.004, 5.0, 10.0]]


def _through_the_door(min_survivors: float, seed: int = 3):
    t = make_tracker("pf", [4.7, 0.0], np.diag([0.0025, 0.09]), walls=DOOR_WALLS, seed=seed, q=0.0,
                     min_survivors=min_survivors)
    t.predict(Step(0.0, 1.0, 90.0, length_std_m=0.02, heading_std_deg=1.0))  # every particle reaches x = 5
    return t


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_pf_spreads_a_few_survivors_by_a_kernel_that_crosses_no_wall(seed):
    """Without the spread the cloud is copies of the few particles that found the door (a
    covariance of ≈ 0 across it); with it the positions spread by the regularised kernel, and
    no particle is moved back through the wall."""
    few = _through_the_door(0.0, seed)
    assert len(np.unique(few.particles[:, :2], axis=0)) < 20
    spread = _through_the_door(100.0, seed)
    assert len(np.unique(spread.particles[:, :2], axis=0)) > 200
    assert (spread.particles[:, 0] > 5.0).all()
    assert np.linalg.eigvalsh(spread.covariance)[0] > 5 * np.linalg.eigvalsh(few.covariance)[0]
    assert np.linalg.eigvalsh(spread.covariance)[0] > 0.005  # (a 7 cm σ at least: h²·P of the cut cloud)


def test_pf_spread_is_idle_while_enough_particles_survive():
    """A walk whose kills leave many survivors is the same to the digit with or without it."""
    plan, area = _corridor()
    runs = []
    for k in (0.0, 100.0):
        t = make_tracker("pf", [2.0, 2.0], np.eye(2) * 0.05, walls=plan.walls, seed=4, min_survivors=k)
        t.set_walkable(area)
        for i in range(30):
            t.predict(Step(i, 0.7, 90.0 - 14.0, length_std_m=0.1, heading_std_deg=3.0))
        runs.append(t)
    np.testing.assert_array_equal(runs[0].particles, runs[1].particles)


def test_pf_spread_restores_exactly():
    import json

    from server.estimation.tracking import tracker_from_dict

    t = _through_the_door(100.0)
    back = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    np.testing.assert_array_equal(back.particles, t.particles)
    for tr in (t, back):
        tr.predict(Step(1.0, 0.7, 90.0))
        tr.update(Fix(6.5, 0.0, 0, np.eye(2)))
    np.testing.assert_array_equal(back.particles, t.particles)
    np.testing.assert_array_equal(back.weights, t.weights)


def test_pf_min_survivors_is_checked():
    from server.estimation.tracking.tuning import BadParam, check_params

    with pytest.raises(ValueError, match="min_survivors"):
        make_tracker("pf", [0.0, 0.0], np.eye(2), min_survivors=-0.5)
    with pytest.raises(BadParam, match="min_survivors"):
        check_params("pf", {"min_survivors": -1})
    assert check_params("pf-xy", {"min_survivors": 20}) == {"min_survivors": 20.0}


def test_the_pfs_learned_bias_is_reported_as_an_angle_though_its_particles_carry_it_unwrapped():
    t = make_tracker("pf", [0.0, 0.0], np.eye(2), seed=1)
    t.particles[:, 2] = 2 * math.pi + math.radians(7.0)  # a bias that drifted a whole turn
    assert t.heading_bias_deg == pytest.approx(7.0)
    t.particles[:, 2] = math.radians(-190.0)
    assert t.heading_bias_deg == pytest.approx(170.0)
