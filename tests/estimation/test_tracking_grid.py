"""The building's grid as a heading reference (``selfcal.Calibrating._observe_grid``): the walls'
grid direction, straight runs, a bias observation every `grid_steps` of a run, its gate, exact persistence."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from server.estimation import building_grid
from server.estimation.session import SessionEstimator
from server.estimation.tracking import make_tracker, selfcal, tracker_from_dict
from server.estimation.types import SiteMap, Step

GAUSSIAN = ["ekf", "ukf", "skpf"]
#: a corridor along x and a cross corridor along y: a grid at 0°
WALLS = [[-60.0, 0.0, 60.0, 0.0], [-60.0, 3.0, 60.0, 3.0], [0.0, -60.0, 0.0, 60.0], [3.0, -60.0, 3.0, 60.0]]
ON = {"grid_sigma_deg": 3.0, "grid_gate_deg": 20.0, "grid_steps": 8}
OFF = {"grid_sigma_deg": 0.0}


def rotated(walls, deg: float) -> list[list[float]]:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return [[c * x1 + s * y1, -s * x1 + c * y1, c * x2 + s * y2, -s * x2 + c * y2] for x1, y1, x2, y2 in walls]


def walk(t, headings, start: int = 0) -> list[float]:
    """Predict with 0.7 m steps along ``headings``; the heading-bias variance after each."""
    out = []
    for k, h in enumerate(headings):
        t.predict(Step(float(start + k), 0.7, float(h), 0.05, 2.0))
        out.append(float(t.state_covariance[2, 2]))
    return out


@pytest.mark.parametrize("deg", [0.0, 10.8, 30.0, -40.0])
def test_the_grid_direction_of_rotated_rectilinear_walls(deg):
    got = building_grid.grid_direction_deg(np.array(rotated(WALLS, deg)))
    assert got is not None
    assert selfcal.wrap_deg(got - deg, 90.0) == pytest.approx(0.0, abs=1e-9)


def test_walls_at_every_angle_have_no_grid():
    walls = np.array([[0.0, 0.0, math.sin(a), math.cos(a)] for a in np.linspace(0, math.pi, 13)[:-1]])
    assert building_grid.grid_direction_deg(walls) is None
    assert building_grid.grid_direction_deg(np.zeros((0, 4))) is None


def test_a_straight_run_grows_until_the_walker_turns():
    run = selfcal.StraightRun()
    for h in (178.0, -176.0, 179.0, -178.0):  # straight across ±180°
        run = run.extended(h)
    assert run.n == 4
    assert abs(selfcal.wrap_deg(run.mean_deg - 180.0)) < 2.0
    run = run.extended(-150.0)  # a turn of 30°: a new run from this step
    assert (run.n, run.mean_deg) == (1, -150.0)


def test_the_bias_observation_is_a_scalar_kalman_update():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(4, 4))
    P = A @ A.T + np.eye(4)
    x = np.array([1.0, 2.0, 0.1, 1.1])
    got_x, got_P = selfcal.observe_bias(tuple(x), tuple(map(tuple, P)), 0.05, 0.003)
    H = np.array([[0.0, 0.0, 1.0, 0.0]])
    K = P @ H.T / (P[2, 2] + 0.003)
    np.testing.assert_allclose(got_x, x + K[:, 0] * 0.05, rtol=1e-12)
    np.testing.assert_allclose(got_P, (np.eye(4) - K @ H) @ P, rtol=1e-12, atol=1e-12)
    assert np.array_equal(np.array(got_P), np.array(got_P).T)


@pytest.mark.parametrize("name", GAUSSIAN)
def test_a_straight_run_observes_the_bias_every_grid_steps(name):
    # The phone's heading is 12° clockwise of the corridor (a true bias of −12°). Without
    # fixes, the run's 8th step observes b ≈ −12°, and so do its 16th and 24th; between them
    # the variance grows by the random walk.
    t = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=WALLS, seed=0, **ON)
    var = walk(t, [102.0] * 30)
    assert t.heading_bias_deg == pytest.approx(-12.0, abs=1.5)
    assert [k for k in range(1, 30) if var[k] < var[k - 1]] == [7, 15, 23]
    assert var[7] < 0.2 * var[6]
    off = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=WALLS, seed=0, **OFF)
    walk(off, [102.0] * 30)
    assert abs(off.heading_bias_deg) < 1e-9


@pytest.mark.parametrize("name", GAUSSIAN)
def test_a_turn_starts_a_new_run(name):
    # 5 steps one way, then 8 after a turn: the observation comes at the 8th step after the turn.
    t = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=WALLS, seed=0, **ON)
    var = walk(t, [102.0] * 5 + [12.0] * 10)
    assert [k for k in range(1, 15) if var[k] < var[k - 1]] == [12]


def test_the_gaussian_trackers_use_the_grid_by_default():
    for name in GAUSSIAN:
        assert make_tracker(name, [0.0, 0.0], np.eye(2)).params["grid_sigma_deg"] == selfcal.GRID_SIGMA_DEG > 0


@pytest.mark.parametrize("name", GAUSSIAN)
def test_a_run_far_from_the_grid_or_a_floor_without_walls_observes_nothing(name):
    for walls, heading in ((WALLS, 135.0), (None, 102.0)):  # 45° off the grid; no plan
        t = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=walls, seed=0, **ON)
        ref = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=walls, seed=0, **OFF)
        walk(t, [heading] * 20)
        walk(ref, [heading] * 20)
        np.testing.assert_array_equal(t.state_mean, ref.state_mean)
        np.testing.assert_array_equal(t.state_covariance, ref.state_covariance)


@pytest.mark.parametrize("name", GAUSSIAN)
def test_a_floor_without_walls_takes_the_grid_its_survey_shows(name):
    # No plan: the floor's grid measured from its survey (set by the session) observes the bias
    # exactly as the same grid's walls would.
    surveyed = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, seed=0, **ON)
    surveyed.set_survey_grid(0.0)
    walled = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=WALLS, seed=0, **ON)
    walk(surveyed, [102.0] * 30)
    walk(walled, [102.0] * 30)
    assert surveyed.heading_bias_deg == pytest.approx(-12.0, abs=1.5)
    np.testing.assert_allclose(surveyed.state_mean, walled.state_mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(surveyed.state_covariance, walled.state_covariance, rtol=1e-12, atol=1e-15)


class NoFixes:
    def fix(self, scan, near):  # pragma: no cover - the walk has no scans
        raise AssertionError("no scan in this walk")


@pytest.mark.parametrize("name", GAUSSIAN)
def test_a_session_gives_its_tracker_the_survey_grid_of_its_floor(name):
    steps = [Step(float(k), 0.7, 102.0, 0.05, 2.0) for k in range(30)]
    learned = {}
    for label, grids in (("this floor", {(0, 0): 0.0}), ("another floor", {(0, 1): 0.0})):
        est = SessionEstimator(name, seed=1, tracker_params=ON)
        est.start([0.0, 1.5], np.eye(2) * 0.1, 0, [], None, "init")
        for k in range(0, 30, 6):  # stored and loaded between batches, as the server does
            est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
            est.apply_batch(steps[k:k + 6], [], NoFixes(), SiteMap(grids=grids))
        learned[label] = est.tracker.heading_bias_deg
    assert learned["this floor"] == pytest.approx(-12.0, abs=1.5)
    assert abs(learned["another floor"]) < 1e-9


@pytest.mark.parametrize("name", GAUSSIAN)
def test_the_walls_grid_comes_before_the_surveys_and_neither_is_stored(name):
    t = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=WALLS, seed=0, **ON)
    t.set_survey_grid(30.0)  # a survey that disagrees with the plan: the plan's walls decide
    walk(t, [102.0] * 8)
    assert t.heading_bias_deg == pytest.approx(-12.0, abs=1.5)
    restored = tracker_from_dict(json.loads(json.dumps(t.to_dict(walls=False))))
    assert restored.survey_grid_deg is None  # it comes from the site before every input, as the walls do


@pytest.mark.parametrize("name", GAUSSIAN)
def test_a_restored_tracker_continues_its_run_exactly(name):
    t = make_tracker(name, [0.0, 1.5], np.eye(2) * 0.1, walls=WALLS, seed=0, **ON)
    walk(t, [100.0] * 5)  # mid-run: the observation is 3 steps away
    restored = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    walk(t, [100.0] * 6, start=5)
    walk(restored, [100.0] * 6, start=5)
    np.testing.assert_array_equal(restored.state_mean, t.state_mean)
    np.testing.assert_array_equal(restored.state_covariance, t.state_covariance)
    assert restored.heading_bias_deg == pytest.approx(-10.0, abs=1.5)


# -- the PF: the grid as a likelihood of each particle's bias ---------------------------------------
#: the grid of WALLS, far from the walk (the walls themselves never kill a particle here)
FAR = [[x1 + 500.0, y1, x2 + 500.0, y2] for x1, y1, x2, y2 in WALLS]
#: the walls' grid observed with a plan, as a plain Gaussian likelihood
PF_WALLS = {**ON, "grid_on_share": 1.0}


def pf(walls=FAR, **params):
    return make_tracker("pf", [0.0, 1.5], np.eye(2) * 0.1, walls=walls, seed=3, **params)


def test_the_pf_learns_a_bias_from_the_walls_grid_without_fixes():
    t, off = pf(**PF_WALLS), pf(**OFF)
    walk(t, [102.0] * 24)
    walk(off, [102.0] * 24)
    assert t.heading_bias_deg == pytest.approx(-12.0, abs=2.0)
    assert math.sqrt(t.state_covariance[2, 2]) < math.radians(4.0)  # narrowed from the 10° prior
    assert abs(off.heading_bias_deg) < 2.0
    assert math.sqrt(off.state_covariance[2, 2]) > math.radians(8.0)


def test_the_pf_keeps_two_biases_90_degrees_apart():
    t = pf(**PF_WALLS)
    half = len(t.particles) // 2
    t.particles[:half, 2] = math.radians(-12.0)
    t.particles[half:, 2] = math.radians(78.0)
    walk(t, [102.0] * 8)  # one observation: both modes are on the grid
    b = np.degrees(t.particles[:, 2])
    near = t.weights[np.abs(b + 12.0) < 10.0].sum()
    far = t.weights[np.abs(b - 78.0) < 10.0].sum()
    assert near + far > 0.99
    assert 0.3 < near < 0.7


def test_the_pf_observes_nothing_off_the_grid_or_without_a_grid():
    for walls, heading in ((FAR, 135.0), (None, 102.0)):  # 45° off the grid; no plan and no survey grid
        t, ref = pf(walls, **PF_WALLS), pf(walls, **OFF)
        walk(t, [heading] * 20)
        walk(ref, [heading] * 20)
        np.testing.assert_array_equal(t.particles, ref.particles)
        np.testing.assert_array_equal(t.weights, ref.weights)


def test_a_restored_pf_continues_its_run_exactly():
    t = pf(**PF_WALLS)
    walk(t, [100.0] * 5)
    state = json.loads(json.dumps(t.to_dict()))
    assert state["state"]["run"][1] == 5
    restored = tracker_from_dict(state)
    walk(t, [100.0] * 6, start=5)
    walk(restored, [100.0] * 6, start=5)
    np.testing.assert_array_equal(restored.particles, t.particles)
    np.testing.assert_array_equal(restored.weights, t.weights)
    del state["state"]["run"]  # stored before the grid: starts a new run
    older = tracker_from_dict(state)
    walk(older, [100.0] * 6, start=5)
    assert older._run.n == 6


def test_the_default_pf_takes_the_survey_grid_on_a_floor_without_a_plan():
    surveyed, bare = pf(None), pf(None)  # default parameters
    surveyed.set_survey_grid(0.0)
    walk(surveyed, [102.0] * 24)
    walk(bare, [102.0] * 24)
    assert surveyed.heading_bias_deg == pytest.approx(-12.0, abs=2.0)
    assert math.sqrt(surveyed.state_covariance[2, 2]) < math.radians(5.0)
    assert abs(bare.heading_bias_deg) < 2.0  # no grid: nothing to observe


def test_with_a_plan_the_default_pf_observes_the_walls_grid_unless_told_not_to():
    default, off, left_out = pf(), pf(**OFF), pf(grid_plan=0)
    for t in (default, off, left_out):
        t.set_survey_grid(30.0)  # the walls' grid (0°) comes first
        walk(t, [102.0] * 16)
    assert default.heading_bias_deg == pytest.approx(-12.0, abs=2.5)
    np.testing.assert_array_equal(left_out.particles, off.particles)
    np.testing.assert_array_equal(left_out.weights, off.weights)


def test_with_a_plan_the_runs_own_heading_noise_widens_the_grid_observation():
    """No Kalman floor with a plan: σ² = 3°² + σh²/n, so a run of steps that declare 20° each
    (σ ≈ 7.7° over 8 steps) narrows the particles' bias less than one of 2° steps (≈ 3.1°)."""
    spread = {}
    for heading_std in (2.0, 20.0):
        t = pf(grid_on_share=1.0, resample_threshold=0.0)
        for k in range(8):
            t.predict(Step(float(k), 0.7, 102.0, 0.05, heading_std))
        spread[heading_std] = math.degrees(math.sqrt(t.state_covariance[2, 2]))
    assert spread[2.0] < 4.0
    assert spread[20.0] > 1.5 * spread[2.0]


def test_a_particle_that_puts_a_run_off_the_grid_is_less_likely_not_ruled_out():
    kept = {}
    for share in (1.0, 0.6):
        t = pf(None, grid_on_share=share, resample_threshold=0.0)
        t.set_survey_grid(0.0)
        t.particles[:, 2] = np.radians(np.linspace(-20.0, 20.0, len(t.particles)))
        walk(t, [100.0] * 8)  # the grid says b = -10°
        b = np.degrees(t.particles[:, 2])
        kept[share] = t.weights[np.abs(b - 10.0) < 2.0].sum()  # particles 20° from the grid's answer
        assert t.heading_bias_deg < -4.0
    assert kept[1.0] < 1e-6
    assert kept[0.6] > 0.005


def test_the_pf_keeps_its_bias_spread_after_a_grid_run_that_disagrees():
    """A 5° bias prior and a run 22° off the grid: reweighted alone, the few particles out there
    leave a bias spread narrower than a Kalman update of the cloud's moments would (most draws);
    with the Kalman floor, never."""
    narrower = 0
    for seed in range(5):
        ratio = {}
        for kappa in (0.0, 1.0):
            t = make_tracker("pf", [0.0, 1.5], np.eye(2) * 0.1, seed=seed, kalman_floor=kappa, bias0_std_deg=5.0,
                             grid_gate_deg=30.0, grid_on_share=1.0, resample_threshold=0.0)
            t.set_survey_grid(0.0)
            walk(t, [112.0] * 7)
            P, s2 = t.state_covariance[2, 2], math.radians(3.0) ** 2
            walk(t, [112.0], start=7)  # the run's 8th step: the observation
            ratio[kappa] = t.state_covariance[2, 2] / (P * s2 / (P + s2))
        narrower += ratio[0.0] < 0.6
        assert ratio[1.0] > 0.9
    assert narrower >= 3
