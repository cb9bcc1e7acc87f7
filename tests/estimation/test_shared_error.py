"""The fixes' shared error in the reported covariance (``tracking/shared_error.py``): the consider
covariance equals the filter's true error covariance, leaves the estimates alone, makes a walk's
NEES consistent when its fixes share their error, and survives a restart exactly."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from server.estimation.session import SessionEstimator
from server.estimation.tracking import make_tracker, selfcal
from server.estimation.tracking.particle_smoother import PathSmoother
from server.estimation.tracking.shared_error import SharedFixError
from server.estimation.tracking.smoother import smooth_track
from server.estimation.types import Beacon, Estimate, Fix, Scan, SiteMap, Step

AUGMENTED = ("ekf", "ukf", "skpf", "pf")


def test_the_excess_is_the_filters_true_error_covariance_when_fixes_share_an_offset():
    """A Kalman filter over [x, y, b, s] that takes each fix as independent (and some narrower than
    they are), against the exact joint propagation of its error and the walk's whitened offset u
    (6 × 6, linear): P + D is the error's true covariance, and C its covariance with u."""
    rng = np.random.default_rng(4)
    P = np.diag([1.0, 1.0, math.radians(5) ** 2, 0.05**2])
    x = np.array([0.0, 0.0, 0.02, 1.03])
    joint = np.zeros((6, 6))
    joint[:4, :4], joint[4:, 4:] = P, np.eye(2)  # the walk's offset: independent of the start
    Q = np.diag([0.01, 0.01, 1e-5, 1e-6])
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    shared = SharedFixError()
    for k in range(40):
        F, _ = selfcal.jacobians(x, 0.7, math.radians(30.0 * k))
        shared.step(x, Step(float(k), 0.7, 30.0 * k))
        P = F @ P @ F.T + Q
        T = np.eye(6)
        T[:4, :4] = F
        joint = T @ joint @ T.T
        joint[:4, :4] += Q
        x = selfcal.move(x, 0.7, math.radians(30.0 * k))
        if k % 3 == 2:
            a = rng.normal(0, 1, (2, 2))
            R = a @ a.T + np.eye(2) * rng.uniform(1, 9)
            rho = float(rng.uniform(0.2, 0.7))
            t_factor = float(rng.uniform(0.25, 1.5))  # a Student-t weight (> 1), a cold start's scale prior (< 1)
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + t_factor * R)
            shared.fix(P, R, t_factor * R, rho)
            A = np.eye(4) - K @ H
            P = A @ P @ A.T + K @ (t_factor * R) @ K.T  # what the filter believes (Joseph form)
            L = np.linalg.cholesky(R)
            T = np.eye(6)
            T[:4, :4], T[:4, 4:] = A, math.sqrt(rho) * K @ L
            joint = T @ joint @ T.T
            joint[:4, :4] += K @ ((1 - rho) * R) @ K.T  # the fix's own noise, the rest of R
            # a wider R_used (t > 1): that much of the filter's K·t·R·Kᵀ is not error, and the consider
            # covariance, which leaves it in P, errs wide by it; a narrower one (t < 1) it counts exactly
            joint[:4, :4] += K @ (max(t_factor - 1, 0.0) * R) @ K.T
    np.testing.assert_allclose(P + shared.D, joint[:4, :4], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(shared.C, joint[:4, 4:], rtol=1e-9, atol=1e-12)
    assert np.linalg.eigvalsh(shared.D[:2, :2]).min() > 0.1  # a real excess, not round-off


def test_a_beacon_range_takes_from_the_excess_what_it_takes_from_the_error():
    """A scalar measurement that shares nothing with the fixes (a beacon range, linearised row h),
    told to the excess by the tracker's covariance before and after it: after a fix that shares its
    error, P + D is still the error's true covariance and C its covariance with the walk's offset
    (the exact joint propagation, 6 × 6)."""
    P = np.diag([4.0, 9.0, math.radians(5) ** 2, 0.05**2])
    P[0, 2] = P[2, 0] = 0.02
    joint = np.zeros((6, 6))
    joint[:4, :4], joint[4:, 4:] = P, np.eye(2)
    shared = SharedFixError()
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    R, rho = np.array([[5.0, 1.0], [1.0, 3.0]]), 0.6
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    shared.fix(P, R, R, rho)
    A = np.eye(4) - K @ H
    P = A @ P @ A.T + K @ R @ K.T
    T = np.eye(6)
    T[:4, :4], T[:4, 4:] = A, math.sqrt(rho) * K @ np.linalg.cholesky(R)
    joint = T @ joint @ T.T
    joint[:4, :4] += K @ ((1 - rho) * R) @ K.T
    for h, var in ((np.array([0.08, -0.06, 0.0, 0.0]), 0.04), (np.array([-0.02, 0.1, 0.0, 0.0]), 0.09)):
        k = P @ h / (h @ P @ h + var)
        A = np.eye(4) - np.outer(k, h)
        P_post = A @ P @ A.T + var * np.outer(k, k)  # (what the tracker's update leaves: Joseph form)
        shared.measured(P, P_post)
        P = P_post
        T = np.eye(6)
        T[:4, :4] = A
        joint = T @ joint @ T.T
        joint[:4, :4] += var * np.outer(k, k)
    np.testing.assert_allclose(P + shared.D, joint[:4, :4], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(shared.C, joint[:4, 4:], rtol=1e-9, atol=1e-12)


def test_a_fix_that_shares_nothing_leaves_the_tracker_alone():
    shared = SharedFixError()
    P = np.eye(4)
    shared.fix(P, np.eye(2), np.eye(2), None)
    shared.fix(P, np.eye(2), np.eye(2), 0.0)
    shared.step(np.array([0.0, 0.0, 0.0, 1.0]), Step(0.0, 0.7, 10.0))
    assert not shared.active and shared.to_dict() is None
    np.testing.assert_array_equal(shared.reported(np.eye(2) * 3), np.eye(2) * 3)


class WalkFixes:
    """Fixes at the truth plus a walk-constant offset (share ``rho``) and white noise, σ ``std``,
    declared with their honest marginal covariance and the share (``None``: undeclared)."""

    def __init__(self, truth: dict[float, np.ndarray], std: float, rho: float, declared: float | None, seed: int):
        rng = np.random.default_rng(seed)
        offset = math.sqrt(rho) * std * rng.standard_normal(2)
        self.by_t = {t: p + offset + math.sqrt(1 - rho) * std * rng.standard_normal(2) for t, p in truth.items()}
        self.cov, self.declared = np.eye(2) * std**2, declared

    def fix(self, scan: Scan, near) -> Fix:
        z = self.by_t[scan.t]
        return Fix(float(z[0]), float(z[1]), 0, self.cov, shared_share=self.declared)


def _walk(seed: int, n: int = 90) -> tuple[list[Step], list[Scan], dict[float, np.ndarray], dict[float, np.ndarray]]:
    """A walk of square legs with a 4° heading bias and noisy steps; truth at every step and scan."""
    rng = np.random.default_rng(seed)
    p, steps, scans, at_step, at_scan = np.zeros(2), [], [], {}, {}
    for k in range(n):
        h = 90.0 * (k // 15)
        p = p + 0.7 * np.array([math.sin(math.radians(h)), math.cos(math.radians(h))])
        steps.append(Step(float(k), 0.7 + rng.normal(0, 0.05), h - 4.0 + rng.normal(0, 3.0), 0.05, 3.0))
        at_step[float(k)] = p
        if k % 2 == 1:
            scans.append(Scan(k + 0.5, {"wifi:a": -60.0}))
            at_scan[k + 0.5] = p
    return steps, scans, at_step, at_scan


def _session(name: str, steps, scans, fixes, **params) -> tuple[SessionEstimator, list[Estimate]]:
    est = SessionEstimator(name, seed=3, tracker_params=params)
    est.start([0.0, 0.0], np.eye(2) * 0.25, 0, [], 0.0, "init")
    return est, list(est.apply_batch(steps, scans, fixes, SiteMap()).estimates)


def _nees(track: list[Estimate], truth: dict[float, np.ndarray]) -> float:
    out = []
    for e in track:
        d = np.array([e.x, e.y]) - truth[e.t]
        out.append(float(d @ np.linalg.solve(np.array(e.covariance), d)))
    return float(np.mean(out))


@pytest.mark.parametrize("name", ["ekf", "skpf"])
def test_declared_shared_fixes_make_the_walks_nees_consistent_and_leave_its_estimates_alone(name):
    """Forty walks whose fixes share 60 % of their error: declared, the reported covariance is
    honest (NEES near 2); undeclared, the tracker claims several times too much. The estimates
    are the same to the bit either way."""
    with_share, without = [], []
    for seed in range(40):
        steps, scans, at_step, at_scan = _walk(seed)
        truth = {**at_step, **at_scan}
        _, declared = _session(name, steps, scans, WalkFixes(at_scan, 3.0, 0.6, 0.6, seed))
        _, blind = _session(name, steps, scans, WalkFixes(at_scan, 3.0, 0.6, None, seed))
        assert [(e.t, e.x, e.y) for e in declared] == [(e.t, e.x, e.y) for e in blind]
        for a, b in zip(declared, blind, strict=True):  # never narrower than the tracker's own
            assert np.linalg.eigvalsh(np.array(a.covariance) - np.array(b.covariance)).min() > -1e-9
        with_share.append(_nees(declared, truth))
        without.append(_nees(blind, truth))
    assert 1.0 < np.mean(with_share) < 3.5
    assert np.mean(without) > 1.8 * np.mean(with_share)


@pytest.mark.parametrize("name", AUGMENTED)
def test_a_session_carrying_the_shared_error_resumes_exactly(name):
    steps, scans, _, at_scan = _walk(1, n=40)
    fixes = WalkFixes(at_scan, 3.0, 0.5, 0.5, 1)
    straight, expected = _session(name, steps, scans, fixes)
    assert straight.shared_error.active
    resumed = SessionEstimator(name, seed=3)
    resumed.start([0.0, 0.0], np.eye(2) * 0.25, 0, [], 0.0, "init")
    got: list[Estimate] = []
    for k in range(0, 40, 7):  # stored through JSON and restored every 7 steps
        resumed = SessionEstimator.from_dict(json.loads(json.dumps(resumed.to_dict())))
        got += resumed.apply_batch(steps[k:k + 7], [s for s in scans if k <= s.t < k + 7], fixes,
                                   SiteMap()).estimates
    assert got == expected


@pytest.mark.parametrize("name", ["ekf", "pf"])
def test_a_session_whose_excess_beacon_ranges_shrink_resumes_exactly(name):
    """Beacon ranges count in the excess (``SharedFixError.measured``): resumed through JSON every 7
    steps, such a session gives the same track, covariances included."""
    steps, scans, _, at_scan = _walk(5, n=40)
    scans = [Scan(s.t, {"wifi:a": -60.0, "ble:b": -64.0}) for s in scans]
    site = SiteMap(beacons={"ble:b": Beacon("ble:b", 0.5, 5.0, 0, -59.0, 2.0)})  # (heard at ≈ 1.8 m: a range)
    fixes = WalkFixes(at_scan, 3.0, 0.5, 0.5, 5)
    straight = SessionEstimator(name, seed=3)
    straight.start([0.0, 0.0], np.eye(2) * 0.25, 0, [], 0.0, "init")
    plain = SessionEstimator(name, seed=3)
    plain.start([0.0, 0.0], np.eye(2) * 0.25, 0, [], 0.0, "init")
    expected = list(straight.apply_batch(steps, scans, fixes, site).estimates)
    without = list(plain.apply_batch(steps, scans, fixes, SiteMap()).estimates)
    assert len(without) == len(expected)
    assert np.trace(straight.shared_error.D[:2, :2]) < 0.9 * np.trace(plain.shared_error.D[:2, :2])  # ranges took some
    resumed = SessionEstimator(name, seed=3)
    resumed.start([0.0, 0.0], np.eye(2) * 0.25, 0, [], 0.0, "init")
    got: list[Estimate] = []
    for k in range(0, 40, 7):
        resumed = SessionEstimator.from_dict(json.loads(json.dumps(resumed.to_dict())))
        got += resumed.apply_batch(steps[k:k + 7], [s for s in scans if k <= s.t < k + 7], fixes, site).estimates
    assert got == expected


def test_a_state_stored_without_the_shared_error_loads_with_none():
    steps, scans, _, at_scan = _walk(2, n=20)
    est, _ = _session("ekf", steps, scans, WalkFixes(at_scan, 3.0, 0.5, 0.5, 2))
    stored = est.to_dict()
    assert stored["shared_error"] is not None
    del stored["shared_error"]  # (as a session stored before it)
    old = SessionEstimator.from_dict(stored)
    assert not old.shared_error.active
    np.testing.assert_array_equal(old.estimate.covariance, est.estimate.covariance)  # its last estimate as stored


def test_a_tracker_that_carries_the_walks_offset_itself_gets_no_excess():
    steps, scans, _, at_scan = _walk(3, n=30)
    est, track = _session("ekf", steps, scans, WalkFixes(at_scan, 3.0, 0.5, 0.5, 3), walk_offset=2)
    assert not est.shared_error.active
    assert np.array(track[-1].covariance) == pytest.approx(est.tracker.covariance)


def test_a_cold_start_begins_with_the_first_fixs_shared_error():
    steps, scans, _, at_scan = _walk(4, n=30)
    shared = SessionEstimator("ekf", seed=3)
    shared.apply_batch(steps[:2], scans[:1], WalkFixes(at_scan, 3.0, 0.5, 0.5, 4), SiteMap())
    blind = SessionEstimator("ekf", seed=3)
    blind.apply_batch(steps[:2], scans[:1], WalkFixes(at_scan, 3.0, 0.5, None, 4), SiteMap())
    # the first fix started both: its error is the walk's offset's, √ρ L u, for the one that declares it
    np.testing.assert_allclose(shared.shared_error.C[:2], math.sqrt(0.5) * 3.0 * np.eye(2))
    assert not blind.shared_error.C.any()


def test_a_cold_starts_fixes_taken_narrower_than_measured_are_counted():
    """A cold start follows its first fixes faster by taking them with a scale prior of 0.25
    (``COLD_FIX_SCALE_PRIOR``); its tracker then claims too much early on. The excess counts what
    that leaves out: over the first estimates of forty cold-started walks with honest, independent
    fixes the tracker's own NEES is well above 2, the reported one near it."""
    reported, own = [], []
    for seed in range(40):
        steps, scans, at_step, at_scan = _walk(seed)
        truth = {**at_step, **at_scan}
        out = SessionEstimator("ekf", seed=3).apply_batch(steps, scans, WalkFixes(at_scan, 3.0, 0.0, None, seed),
                                                          SiteMap())
        for e, s in list(zip(out.estimates, out.states, strict=True))[:10]:
            d = np.array([e.x, e.y]) - truth[e.t]
            reported.append(float(d @ np.linalg.solve(np.array(e.covariance), d)))
            own.append(float(d @ np.linalg.solve(np.array(s.covariance)[:2, :2], d)))
    assert np.mean(own) > 3.5
    assert 1.0 < np.mean(reported) < 3.0


def test_the_smoothed_track_keeps_the_excess_of_each_estimate():
    steps, scans, _, at_scan = _walk(5, n=40)
    est = SessionEstimator("ekf", seed=3)
    est.start([0.0, 0.0], np.eye(2) * 0.25, 0, [], 0.0, "init")
    first = est.estimate
    out = est.apply_batch(steps, scans, WalkFixes(at_scan, 3.0, 0.5, 0.5, 5), SiteMap())
    track = list(out.estimates)
    states = list(out.states)
    own = [Estimate.of(e.t, (e.x, e.y), np.array(s.covariance)[:2, :2], e.floor, e.source) for e, s in
           zip(track, states, strict=True)]
    with_excess, without = smooth_track(track, None, states), smooth_track(own, None, states)
    for i, (a, b) in enumerate(zip(with_excess, without, strict=True)):
        assert (a.x, a.y) == pytest.approx((b.x, b.y), abs=1e-12)
        j = i  # every estimate of a time index gets the excess of its filtered (last) estimate
        while j + 1 < len(track) and track[j + 1].source != "step":
            j += 1
        excess = np.array(track[j].covariance) - np.array(own[j].covariance)
        np.testing.assert_allclose(np.array(a.covariance) - np.array(b.covariance), excess, atol=1e-9)
    assert first is not None and np.trace(np.array(track[-1].covariance) - np.array(own[-1].covariance)) > 1.0


def _particle_smoothed(excess: np.ndarray | None):
    pf = make_tracker("pf-xy", [0.0, 0.0], np.eye(2), seed=3, n_particles=300)
    pf.lineage = np.arange(300)  # (as a replay: the descent is kept)
    smoother = PathSmoother(lag=5)
    for k in range(8):
        pf.predict(Step(float(k), 0.7, 90.0))
        pf.update(Fix(0.7 * (k + 1), 0.0, 0, np.eye(2) * 0.5))
        smoother.observe(pf, pf.covariance, excess)
    return smoother.finish()


def test_the_particle_smoother_keeps_the_excess():
    excess = np.array([[2.0, 0.5], [0.5, 1.0]])
    for a, b in zip(_particle_smoothed(None), _particle_smoothed(excess), strict=True):
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_allclose(b.covariance - a.covariance, excess, atol=1e-12)
