"""The session's learned fix-noise scale and the Student-t fix weighting (tracking/fixnoise.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from server.estimation.session import GATE_D2, SessionEstimator
from server.estimation.tracking.fixnoise import SAMPLE_MAX_RATIO, STUDENT_NU, FixNoiseScale, student_t_factor
from server.estimation.types import Area, Fix, Scan, SiteMap, Step


@pytest.mark.parametrize("true_scale", [1.0, 4.0, 9.0])
def test_scale_matches_the_innovations_it_is_fed(true_scale):
    rng = np.random.default_rng(3)
    P, R = np.diag([0.5, 1.5]), np.array([[2.0, 0.5], [0.5, 1.0]])
    S = P + true_scale * R
    est = FixNoiseScale()
    scales = []
    for _ in range(400):
        est.observe(rng.multivariate_normal([0, 0], S), P, R)
        scales.append(est.scale)
    # a window of ~30 fixes: the running value scatters, its average over the walk does not
    assert np.mean(scales[100:]) == pytest.approx(true_scale, rel=0.2)


def test_innovations_smaller_than_calibrated_never_make_a_session_trust_its_fixes_more():
    """Fixes that agree with the estimate (a tracker following fixes biased together) teach
    nothing below the calibration: the scale stays at 1, a cold start's at its 0.25 prior."""
    P, R = np.eye(2) * 4.0, np.eye(2) * 100.0
    known, cold = FixNoiseScale(), FixNoiseScale(prior=0.25)
    for _ in range(200):
        known.observe(np.zeros(2), P, R)
        cold.observe(np.zeros(2), P, R)
    assert known.scale == 1.0 and known.total == 0.0  # every sample clipped at 0: pulled to the bound
    assert cold.scale == 0.25
    wider = FixNoiseScale()
    for _ in range(200):
        wider.observe(np.array([30.0, 30.0]), P, R)
    assert wider.scale > 5.0  # worse than calibrated is still learned


def test_one_gross_outlier_moves_the_scale_by_a_bounded_step():
    P, R = np.eye(2) * 0.5, np.eye(2)
    est = FixNoiseScale()
    rng = np.random.default_rng(0)
    for _ in range(60):
        est.observe(rng.multivariate_normal([0, 0], P + R), P, R)
    before = est.scale
    est.observe(np.array([80.0, -60.0]), P, R)  # 100 m off with a 1 m fix std
    assert est.scale - before <= SAMPLE_MAX_RATIO * before / est.weight + 1e-9
    assert est.scale < 1.3 * before


def test_a_run_of_large_innovations_grows_the_scale_past_one_samples_clip():
    P, R = np.eye(2) * 0.5, np.eye(2)
    est = FixNoiseScale()
    for _ in range(40):
        est.observe(np.array([8.0, 8.0]), P, R)  # sample 63.5 every time
    assert est.scale > 2 * SAMPLE_MAX_RATIO


def test_a_stored_scale_round_trips_and_a_missing_one_starts_at_the_prior():
    est = FixNoiseScale()
    est.observe(np.array([5.0, 5.0]), np.eye(2), np.eye(2))
    assert FixNoiseScale.from_list(json.loads(json.dumps(est.to_list()))).scale == est.scale
    assert FixNoiseScale.from_list(None).scale == 1.0


def test_student_t_factor_keeps_near_fixes_and_discounts_far_ones():
    assert student_t_factor(0.0) == 1.0
    assert student_t_factor(2.0) == 1.0
    factors = [student_t_factor(d2) for d2 in (3.0, 6.0, 10.0, GATE_D2)]
    assert factors == sorted(factors) and factors[0] > 1.0
    assert student_t_factor(GATE_D2) == pytest.approx((STUDENT_NU + GATE_D2) / (STUDENT_NU + 2.0))


class OverconfidentFixes:
    """Unbiased fixes whose claimed covariance is 9× too small (std 3 m claimed as 1 m)."""

    def __init__(self, truth_at: dict[float, np.ndarray], seed: int):
        self.rng = np.random.default_rng(seed)
        self.truth_at = truth_at

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        z = self.truth_at[scan.t] + 3.0 * self.rng.standard_normal(2)
        return Fix(float(z[0]), float(z[1]), 0, np.eye(2))


def straight_walk(n_steps: int):
    steps, scans, truth_at = [], [], {}
    for k in range(1, n_steps + 1):
        t = 0.5 * k
        steps.append(Step(t, 0.7, 90.0))  # east, exact PDR
        if k % 2 == 0:
            scans.append(Scan(t + 0.1, {"wifi:a": -60.0}))
            truth_at[t + 0.1] = np.array([0.7 * k, 0.0])
    return steps, scans, truth_at


def run_batches(est: SessionEstimator, steps, scans, fixes, through_json: bool = False):
    """Feed the walk in batches of 8 steps; yields each batch's outcome."""
    for b in range(0, len(steps), 8):
        batch_steps = steps[b:b + 8]
        t0, t1 = batch_steps[0].t, batch_steps[-1].t + 0.5
        if through_json:
            est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        yield est, est.apply_batch(batch_steps, [s for s in scans if t0 <= s.t < t1], fixes, SiteMap())


@pytest.mark.parametrize("name", ["ekf", "ukf", "pf", "skpf"])
def test_a_session_learns_that_its_fixes_scatter_more_than_they_claim(name):
    steps, scans, truth_at = straight_walk(400)
    est = SessionEstimator(name, seed=1)
    est.start([0.0, 0.0], np.eye(2) * 0.1, 0, [], None, "init")
    last = est
    for last, _ in run_batches(est, steps, scans, OverconfidentFixes(truth_at, seed=5), through_json=True):
        assert last.fix_noise.scale <= 14.0
    est = last
    # claimed variance 1 m², true 9 m²; the tracker's own covariance adds to the innovations
    assert 5.0 < est.fix_noise.scale < 14.0


def test_refusals_stay_rare_when_the_fixes_are_overconfident():
    steps, scans, truth_at = straight_walk(600)
    est = SessionEstimator("ekf", seed=1)
    est.start([0.0, 0.0], np.eye(2) * 0.1, 0, [], None, "init")
    outcomes = [out for _, out in run_batches(est, steps, scans, OverconfidentFixes(truth_at, seed=9))]
    refused = sum(len(o.rejected_fixes) for o in outcomes)
    total = sum(o.applied_scans for o in outcomes)
    assert total > 250
    assert refused / total < 0.05


@pytest.mark.parametrize("name", ["ekf-xy", "kf", "fkf"])
def test_a_seed_form_takes_the_fix_as_the_model_gives_it(name):
    """Covariance matching needs an honest tracker covariance; a seed form's is not (it does
    not model the PDR's bias), so it neither learns a scale nor weighs fixes as a Student-t."""
    steps, scans, truth_at = straight_walk(200)
    est = SessionEstimator(name, seed=1)
    est.start([0.0, 0.0], np.eye(2) * 0.1, 0, [], None, "init")
    for _ in run_batches(est, steps, scans, OverconfidentFixes(truth_at, seed=5)):
        pass
    assert est.fix_noise.scale == 1.0 and est.fix_noise.weight == 0.0
