"""A session's start direction known independently of the phone's compass (``InitialHeading``, the
API's ``initial.heading_deg`` with ``heading_std_deg``): at the first step it is one observation of
the heading bias b = heading − the step's heading, variance σ² + the step's white heading σ²."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from server.estimation.session import SessionEstimator
from server.estimation.tracking import selfcal
from server.estimation.types import InitialHeading, Step

#: the phone reports 50° while the walker goes 90°: its heading bias is +40°
REPORTED, TRUE = 50.0, 90.0


def _session(name: str, heading: InitialHeading | None, **params) -> SessionEstimator:
    est = SessionEstimator(name, seed=3, tracker_params=params)
    est.start([0.0, 0.0], None, 0, [], None, "init", heading=heading)
    return est


def _expected_bias_deg(std_deg: float, step_std_deg: float = 5.0) -> float:
    """By hand: prior b ~ N(0, 10°²), one observation z = 40° with variance std² + step_std²."""
    prior = selfcal.BIAS0_STD_DEG**2
    return (TRUE - REPORTED) * prior / (prior + std_deg**2 + step_std_deg**2)


@pytest.mark.parametrize("name", ["ekf", "ukf", "skpf"])
@pytest.mark.parametrize("std", [1.0, 5.0])
def test_the_gaussian_filters_take_the_start_direction_as_one_kalman_update_of_the_bias(name, std):
    est = _session(name, InitialHeading(TRUE, std))
    est.step(Step(0.5, 0.7, REPORTED))
    assert est.tracker.heading_bias_deg == pytest.approx(_expected_bias_deg(std), abs=1e-6)
    # the bias's variance after it: (1 − K)·σb0² (then the step's walk σ² on top)
    prior = math.radians(selfcal.BIAS0_STD_DEG) ** 2
    obs = math.radians(std) ** 2 + math.radians(5.0) ** 2
    walk = math.radians(selfcal.BIAS_WALK_DEG) ** 2
    assert est.tracker.state_covariance[2, 2] == pytest.approx(prior * obs / (prior + obs) + walk, rel=1e-6)


def test_the_step_s_declared_heading_noise_counts_in_the_observation():
    est = _session("ekf", InitialHeading(TRUE, 2.0))
    est.step(Step(0.5, 0.7, REPORTED, heading_std_deg=12.0))
    assert est.tracker.heading_bias_deg == pytest.approx(_expected_bias_deg(2.0, 12.0), abs=1e-6)


def test_the_pf_moves_its_cloud_s_bias_as_the_update_moves_the_moments_and_keeps_every_particle():
    est = _session("pf", InitialHeading(TRUE + 20.0, 1.0))  # 60° off: 6σ of the prior, no particle there
    before = est.tracker.particles[:, 2].copy()
    weights = est.tracker.weights.copy()
    est.tracker.observe_heading(Step(0.5, 0.7, REPORTED), TRUE + 20.0, 1.0)
    b = est.tracker.particles[:, 2]
    m0, v0 = weights @ before, weights @ (before - weights @ before) ** 2
    var = math.radians(1.0) ** 2 + math.radians(5.0) ** 2
    k = v0 / (v0 + var)
    assert weights @ b == pytest.approx(m0 + k * (math.radians(60.0) - m0), abs=2e-3)  # (the stored grid's rounding)
    assert weights @ (b - weights @ b) ** 2 == pytest.approx((1 - k) * v0, rel=0.02)
    np.testing.assert_array_equal(est.tracker.weights, weights)
    assert math.degrees(weights @ b) > 45.0  # the cloud went where the observation says, not died


def test_a_walk_told_its_start_direction_follows_it_and_a_seed_form_ignores_it():
    """Twenty steps with no fix: the self-calibrating EKF told the true start ends nearer the truth;
    the seed forms (no bias state) are exactly as without it."""
    truth = 20 * 0.7 * np.array([math.sin(math.radians(TRUE)), math.cos(math.radians(TRUE))])
    ends = {}
    for name in ("ekf", "ekf-xy", "kf"):
        for told in (None, InitialHeading(TRUE, 2.0)):
            est = _session(name, told)
            for k in range(20):
                est.step(Step(0.5 * (k + 1), 0.7, REPORTED))
            ends[name, told is not None] = np.array([est.estimate.x, est.estimate.y])
    assert np.linalg.norm(ends["ekf", True] - truth) < 0.5 * np.linalg.norm(ends["ekf", False] - truth)
    for name in ("ekf-xy", "kf"):
        np.testing.assert_array_equal(ends[name, True], ends[name, False])


def test_the_start_direction_waits_in_the_stored_state_until_the_first_step():
    est = _session("ukf", InitialHeading(TRUE, 2.0))
    stored = json.loads(json.dumps(est.to_dict()))
    assert stored["initial_heading"] == [TRUE, 2.0]
    restored = SessionEstimator.from_dict(stored)  # (a restart between the open and the first batch)
    restored.step(Step(0.5, 0.7, REPORTED))
    assert restored.tracker.heading_bias_deg == pytest.approx(_expected_bias_deg(2.0), abs=1e-6)
    assert "initial_heading" not in restored.to_dict()  # taken once
    restored.step(Step(1.0, 0.7, REPORTED))
    assert restored.tracker.heading_bias_deg == pytest.approx(_expected_bias_deg(2.0), abs=1e-6)


def test_a_state_stored_before_the_start_direction_existed_loads_without_one():
    est = _session("ekf", None)
    stored = est.to_dict()
    assert "initial_heading" not in stored
    assert SessionEstimator.from_dict(stored).initial_heading is None
