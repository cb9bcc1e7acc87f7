"""Particle filter: walls kill particles, likelihood weighting, resampling equals filterpy."""

import numpy as np
import pytest
from filterpy.monte_carlo import systematic_resample as filterpy_systematic_resample

from server.estimation.tracking import make_tracker
from server.estimation.tracking.geometry import crosses_walls
from server.estimation.tracking.resampling import systematic_resample
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
    np.testing.assert_allclose(t.weights, lik / lik.sum(), rtol=1e-10)
    np.testing.assert_allclose(t.mean, (lik / lik.sum()) @ before, rtol=1e-10)


def test_pf_resamples_when_degenerate():
    t = make_tracker("pf-xy", [0, 0], np.eye(2), seed=3)
    t.update(Fix(1.0, 0.0, 0, np.eye(2) * 0.01))
    np.testing.assert_allclose(t.weights, 1.0 / 1000)
    # exact posterior mean: 1·1/(1 + 0.01) ≈ 0.99
    assert abs(t.mean[0] - 0.99) < 0.1
    assert len(np.unique(t.particles[:, 0])) < 200  # collapsed onto the few likely ones


def test_pf_range_update_gated_and_wall_side():
    t = make_tracker("pf-xy", [0, 0.5], np.eye(2), seed=4)
    assert t.update_range([0, 0], 3.5, 0.5) is False
    assert t.update_range([0, 0], 0.5, 0.2, on_wall=[-5, 0, 5, 0]) is True
    assert np.all(t.particles[np.abs(t.particles[:, 0]) <= 5, 1] > 0)
