"""UKF and SKPF pinned to hand-computed one-step results and to filterpy."""

import math

import numpy as np
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

from server.estimation.tracking import make_tracker
from server.estimation.types import Fix, Step

EXACT = {"length_std_m": 0.0, "heading_std_deg": 0.0}


def test_ukf_linear_case_equals_kf_by_hand():
    # Same numbers as the KF test: with exact steps the step model is a shift, the UT
    # is exact, so x⁻ = (1, 0), P⁻ = I + 0.5·I; fix (2, 1), R = I → x⁺ = (1.6, 0.6), P⁺ = 0.6·I.
    t = make_tracker("ukf-xy", [0, 0], np.eye(2), q=0.5)
    t.predict(Step(0, 1.0, 90.0, **EXACT))
    np.testing.assert_allclose(t.mean, [1.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(t.covariance, 1.5 * np.eye(2), atol=1e-9)
    t.update(Fix(2.0, 1.0, 0, np.eye(2)))
    np.testing.assert_allclose(t.mean, [1.6, 0.6], atol=1e-9)
    np.testing.assert_allclose(t.covariance, 0.6 * np.eye(2), atol=1e-9)


def test_ukf_matches_filterpy_ukf_run_by_hand():
    rng = np.random.default_rng(5)
    pts = MerweScaledSigmaPoints(2, alpha=1.0, beta=2.0, kappa=0.0)
    ref = UnscentedKalmanFilter(2, 2, 1.0, hx=lambda x: x, fx=lambda x, dt, u: x + u, points=pts)
    ref.x = np.array([0.5, -1.0])
    ref.P = np.array([[1.0, 0.3], [0.3, 2.0]])
    ref.Q = 0.2 * np.eye(2)
    t = make_tracker("ukf-xy", [0.5, -1.0], [[1.0, 0.3], [0.3, 2.0]], q=0.2)
    for k in range(10):
        step = Step(k, 0.7, 360 * rng.random(), **EXACT)
        h = math.radians(step.heading_deg)
        ref.predict(u=np.array([0.7 * math.sin(h), 0.7 * math.cos(h)]))
        t.predict(step)
        R = np.diag(rng.uniform(0.5, 3.0, 2))
        z = rng.normal(size=2)
        ref.update(z, R=R)
        t.update(Fix(z[0], z[1], 0, R))
        np.testing.assert_allclose(t.mean, ref.x, atol=1e-9)
        np.testing.assert_allclose(t.covariance, ref.P, atol=1e-9)


def test_ukf_captures_heading_nonlinearity():
    # Heading N(0°, (40°)²), d = 2: E[dy] = 2·exp(−σ²/2) < 2 — the EKF keeps 2, the UKF
    # shrinks it towards the Monte Carlo value.
    step = Step(0, 2.0, 0.0, length_std_m=0.0, heading_std_deg=40.0)
    ukf = make_tracker("ukf-xy", [0, 0], np.eye(2) * 1e-4, q=0.0)
    ekf = make_tracker("ekf-xy", [0, 0], np.eye(2) * 1e-4, q=0.0)
    ukf.predict(step)
    ekf.predict(step)
    rng = np.random.default_rng(0)
    h = rng.normal(0.0, math.radians(40.0), 200_000)
    mc_mean_y = float(np.mean(2.0 * np.cos(h)))
    assert ekf.mean[1] == 2.0
    assert abs(ukf.mean[1] - mc_mean_y) < 0.5 * abs(ekf.mean[1] - mc_mean_y)


def test_skpf_one_step_by_hand():
    # x0 = (0, 0), P0 = I, exact step 1 m north, q = 1 → x⁻ = (0, 1), P⁻ = I + I = 2·I.
    # Sigma points x⁻ ± √2·√2 along each axis: (2, 1), (0, 3), (−2, 1), (0, −1), w = 1/4.
    # Fix z = (1, 1), R = 2·I: ẑ = (0, 1), S = P⁻ + R = 4·I, Pxz = 2·I, K = 0.5·I,
    # P⁺ = 2·I − 0.5·4·0.5·I = I.
    # Likelihoods N(z; χ_i, 2I) ∝ exp(−‖z − χ_i‖²/4): a = e^−0.25, b = e^−1.25 (twice), c = e^−2.25;
    # x⁺ = (2a − 2c, a + 3b + c − b)/(a + 2b + c) = (2(a − c)/(a + 2b + c), 1).
    t = make_tracker("skpf-xy", [0, 0], np.eye(2), q=1.0)
    t.predict(Step(0, 1.0, 0.0, **EXACT))
    np.testing.assert_allclose(t.mean, [0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(t.covariance, 2 * np.eye(2), atol=1e-12)
    t.update(Fix(1.0, 1.0, 0, 2 * np.eye(2)))
    a, b, c = math.exp(-0.25), math.exp(-1.25), math.exp(-2.25)
    np.testing.assert_allclose(t.mean, [2 * (a - c) / (a + 2 * b + c), 1.0], atol=1e-12)
    np.testing.assert_allclose(t.covariance, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(t.last_weights, np.array([a, b, c, b]) / (a + 2 * b + c), atol=1e-12)


def test_skpf_covariance_matches_filterpy_kf_for_linear_model():
    # For h(x) = x the unscented S and K are the KF's, so P follows a filterpy KF exactly.
    rng = np.random.default_rng(2)
    ref = KalmanFilter(dim_x=2, dim_z=2)
    ref.x = np.zeros(2)
    ref.P = np.array([[2.0, 0.4], [0.4, 1.0]])
    ref.H = np.eye(2)
    t = make_tracker("skpf-xy", [0, 0], ref.P.copy(), q=0.1)
    for k in range(8):
        step = Step(k, 0.7, 360 * rng.random(), length_std_m=0.1, heading_std_deg=8.0)
        t.predict(step)
        from server.estimation.tracking.motion import step_noise_cov

        ref.predict(Q=step_noise_cov(step) + 0.1 * np.eye(2))
        R = np.diag(rng.uniform(0.5, 3.0, 2))
        t.update(Fix(*rng.normal(size=2), 0, R))
        ref.update(np.zeros(2), R=R)
        np.testing.assert_allclose(t.covariance, ref.P, atol=1e-10)


def test_skpf_mean_is_likelihood_weighted_not_kalman():
    # The posterior mean stays inside the sigma-point hull, unlike the KF's K·y.
    t = make_tracker("skpf-xy", [0, 0], np.eye(2), q=0.0)
    t.update(Fix(100.0, 0.0, 0, np.eye(2)))
    assert t.mean[0] <= math.sqrt(2) + 1e-12
    assert t.mean[0] > 1.4


def test_skpf_sigma_points_are_filterpy_julier_kappa0_without_centre():
    from filterpy.kalman import JulierSigmaPoints

    from server.estimation.tracking.skpf import symmetric_sigma_points

    x = np.array([1.0, -2.0])
    P = np.array([[2.0, 0.7], [0.7, 0.9]])
    ref = JulierSigmaPoints(2, kappa=0.0)
    sig, w = symmetric_sigma_points(x, P)
    np.testing.assert_allclose(sig, ref.sigma_points(x, P)[1:], atol=1e-12)
    np.testing.assert_allclose(w, ref.Wm[1:], atol=1e-15)
    assert ref.Wm[0] == 0 and np.isclose(w.sum(), 1.0)
    np.testing.assert_allclose((w[:, None] * (sig - x)).T @ (sig - x), P, atol=1e-12)


def _skpf_reference(x, P, items, q):
    """The SKPF written with filterpy's sigma points and unscented transform (the
    formulas of DESIGN.md, as the tracker was first written) — the closed-form tracker
    must follow it to round-off."""
    from filterpy.kalman import JulierSigmaPoints, unscented_transform

    from server.estimation.tracking.base import fix_cov
    from server.estimation.tracking.motion import step_noise_cov
    from server.estimation.types import step_displacement

    pts = JulierSigmaPoints(2, kappa=0.0)
    w = pts.Wm[1:]
    out = []
    for item in items:
        sig = pts.sigma_points(x, P)[1:]
        if isinstance(item, Step):
            sig = sig + step_displacement(item.length_m, item.heading_deg)
            x, P = unscented_transform(sig, w, w, step_noise_cov(item) + q * np.eye(2))
        else:
            R = fix_cov(item.covariance)
            z_hat, S = unscented_transform(sig, w, w, R)
            Pxz = (w[:, None] * (sig - x)).T @ (sig - z_hat)
            K = Pxz @ np.linalg.inv(S)
            diff = item.mean - sig
            lw = -0.5 * np.einsum("ij,jk,ik->i", diff, np.linalg.inv(R), diff)
            lik = np.exp(lw - lw.max())
            lik /= lik.sum()
            x, P = lik @ sig, P - K @ S @ K.T
        P = 0.5 * (P + P.T)
        out.append((np.array(x), np.array(P)))
    return out


def test_skpf_closed_form_follows_filterpy_reference():
    rng = np.random.default_rng(9)
    P0 = np.array([[1.5, -0.4], [-0.4, 0.8]])
    items = []
    for k in range(60):
        items.append(Step(k, 0.5 + 0.4 * rng.random(), 360 * rng.random(), 0.1 * rng.random(), 10 * rng.random()))
        if k % 2:
            A = rng.normal(size=(2, 2))
            R = A @ A.T + 0.2 * np.eye(2) if k % 3 else np.diag([0.0, 2.0])  # some need the floor
            items.append(Fix(*rng.normal(0, 3, 2), 0, R))
    t = make_tracker("skpf-xy", [0.3, -0.2], P0, q=0.05)
    ref = _skpf_reference(np.array([0.3, -0.2]), P0, items, 0.05)
    for item, (x, P) in zip(items, ref, strict=True):
        t.predict(item) if isinstance(item, Step) else t.update(item)
        np.testing.assert_allclose(t.mean, x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(t.covariance, P, rtol=1e-9, atol=1e-9)
