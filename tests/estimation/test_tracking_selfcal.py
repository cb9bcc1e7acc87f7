"""The self-calibrating trackers (state [x, y, heading bias, step scale]): pinned to
hand-computed steps and to filterpy, learning a heading bias on a simulated walk, exact
persistence, and stored states of the version-1 format."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from filterpy.kalman import (
    ExtendedKalmanFilter,
    JulierSigmaPoints,
    MerweScaledSigmaPoints,
    UnscentedKalmanFilter,
    unscented_transform,
)

from server.estimation.session import SessionEstimator
from server.estimation.tracking import (
    EKFXYTracker,
    ParticleFilterXYTracker,
    SKPFXYTracker,
    UKFXYTracker,
    make_tracker,
    selfcal,
    tracker_from_dict,
)
from server.estimation.types import Fix, Step
from tests.helpers.simulate import run_tracker, simulate_walk

AUGMENTED = ["ekf", "ukf", "pf", "skpf"]
#: no random walks, no jitter: the one-step numbers below are exact
STILL = {"q": 0.0, "bias_walk_deg": 0.0, "scale_walk": 0.0, "bias0_std_deg": math.degrees(0.1), "scale0_std": 0.1}


def test_ekf_one_step_and_fix_by_hand():
    # x0 = (0, 0, b = 0, s = 1), P0 = diag(1, 1, 0.01, 0.01). Step d = 2 m, h = 0°, σd = 0.1 m,
    # σh = 0.1 rad. F = [[1, 0, s·d·cos a, d·sin a], [0, 1, −s·d·sin a, d·cos a], e3, e4] at
    # a = h + b = 0 → F[0, 2] = 2, F[1, 3] = 2; G = [[s·sin a, s·d·cos a], [s·cos a, −s·d·sin a], 0, 0]
    # = [[0, 2], [1, 0], 0, 0]. P⁻ = F P Fᵀ + G diag(0.01, 0.01) Gᵀ:
    #   P⁻[0, 0] = 1 + 4·0.01 + 4·0.01 = 1.08, P⁻[1, 1] = 1 + 4·0.01 + 0.01 = 1.05,
    #   P⁻[0, 2] = 2·0.01 = 0.02, P⁻[1, 3] = 0.02, P⁻[2, 2] = P⁻[3, 3] = 0.01.
    t = make_tracker("ekf", [0, 0], np.eye(2), **STILL)
    t.predict(Step(0, 2.0, 0.0, length_std_m=0.1, heading_std_deg=math.degrees(0.1)))
    P = np.array([[1.08, 0, 0.02, 0], [0, 1.05, 0, 0.02], [0.02, 0, 0.01, 0], [0, 0.02, 0, 0.01]])
    np.testing.assert_allclose(t.state_mean, [0, 2, 0, 1], atol=1e-12)
    np.testing.assert_allclose(t.state_covariance, P, atol=1e-12)
    # Fix (1, 2), R = I: S = diag(2.08, 2.05), K = P[:, :2] S⁻¹, innovation (1, 0).
    # The fix lies east of a walker heading north: the bias learned is clockwise (positive).
    t.update(Fix(1.0, 2.0, 0, np.eye(2)))
    np.testing.assert_allclose(t.state_mean, [1.08 / 2.08, 2.0, 0.02 / 2.08, 1.0], atol=1e-12)
    assert t.heading_bias_deg == pytest.approx(math.degrees(0.02 / 2.08))
    np.testing.assert_allclose(t.state_covariance[0, 0], 1.08 - 1.08**2 / 2.08, atol=1e-12)
    np.testing.assert_allclose(t.state_covariance[0, 2], 0.02 - 1.08 * 0.02 / 2.08, atol=1e-12)
    np.testing.assert_allclose(t.state_covariance[2, 2], 0.01 - 0.02**2 / 2.08, atol=1e-12)
    np.testing.assert_allclose(t.covariance, t.state_covariance[:2, :2])


def test_ekf_matches_filterpy_ekf_with_the_same_jacobians():
    rng = np.random.default_rng(3)
    t = make_tracker("ekf", [0.5, -1.0], [[1.0, 0.3], [0.3, 2.0]])
    ref = ExtendedKalmanFilter(dim_x=4, dim_z=2)
    ref.x, ref.P = t.state_mean, t.state_covariance
    Q = selfcal.process_noise(t.params["q"], t.params)
    for k in range(15):
        step = Step(k, 0.6 + 0.2 * rng.random(), 360 * rng.random(), 0.1, 6.0)
        h = math.radians(step.heading_deg)
        F, G = selfcal.jacobians(ref.x, step.length_m, h)
        ref.x = selfcal.move(ref.x, step.length_m, h)
        ref.P = F @ ref.P @ F.T + G @ np.diag([0.01, math.radians(6.0) ** 2]) @ G.T + Q
        t.predict(step)
        z, R = rng.normal(size=2) + ref.x[:2], np.diag(rng.uniform(0.5, 3.0, 2))
        ref.update(z, lambda x: np.eye(2, 4), lambda x: x[:2], R=R)
        t.update(Fix(z[0], z[1], 0, R))
        np.testing.assert_allclose(t.state_mean, ref.x, atol=1e-9)
        np.testing.assert_allclose(t.state_covariance, ref.P, atol=1e-9)


def test_ukf_update_matches_filterpy_ukf_and_its_predict_the_ekf_when_nearly_linear():
    t = make_tracker("ukf", [0.5, -1.0], [[1.0, 0.3], [0.3, 2.0]])
    ref = UnscentedKalmanFilter(4, 2, 1.0, hx=lambda x: x[:2], fx=lambda x, dt: x,
                                points=MerweScaledSigmaPoints(4, alpha=1.0, beta=2.0, kappa=0.0))
    ref.x, ref.P, ref.Q = t.state_mean, t.state_covariance, np.zeros((4, 4))
    ref.predict()  # fx = identity, Q = 0: only sets the sigma points
    R = np.array([[1.5, 0.2], [0.2, 0.8]])
    ref.update(np.array([1.0, 0.5]), R=R)
    t.update(Fix(1.0, 0.5, 0, R))
    np.testing.assert_allclose(t.state_mean, ref.x, atol=1e-9)
    np.testing.assert_allclose(t.state_covariance, ref.P, atol=1e-9)
    # Small uncertainty everywhere: the unscented and the linearised predictions agree up to
    # the second-order terms the EKF drops (d·σh²/2 ≈ 3·10⁻⁵ m here).
    tiny = dict(STILL, bias0_std_deg=0.01, scale0_std=1e-4)
    ukf, ekf = (make_tracker(n, [0, 0], np.eye(2) * 1e-4, **tiny) for n in ("ukf", "ekf"))
    for tr in (ukf, ekf):
        tr.predict(Step(0, 0.7, 30.0, 0.01, 0.5))
    np.testing.assert_allclose(ukf.state_mean, ekf.state_mean, atol=5e-5)
    np.testing.assert_allclose(ukf.state_covariance, ekf.state_covariance, rtol=1e-3, atol=1e-9)


def test_skpf_predict_is_the_unscented_transform_of_its_eight_sigma_points():
    t = make_tracker("skpf", [0.3, -0.2], [[1.0, 0.2], [0.2, 0.5]], bias0_std_deg=8.0, scale0_std=0.1)
    t.predict(Step(0, 0.7, 40.0, 0.1, 5.0))  # some correlation between position and b, s
    x, P = t.state_mean, t.state_covariance
    step = Step(1, 0.8, 120.0, 0.1, 5.0)
    pts = JulierSigmaPoints(4, kappa=0.0)
    sig = pts.sigma_points(x, P)
    assert pts.Wm[0] == 0.0  # the centre point has no weight: the 8 symmetric ones remain
    moved = selfcal.move_many(sig, step.length_m, math.radians(step.heading_deg))
    m, C = unscented_transform(moved, pts.Wm, pts.Wc, selfcal.process_noise(t.params["q"], t.params))
    _, G = selfcal.jacobians(m, step.length_m, math.radians(step.heading_deg))
    C = C + G @ np.diag([0.01, math.radians(5.0) ** 2]) @ G.T
    t.predict(step)
    np.testing.assert_allclose(t.state_mean, m, atol=1e-12)
    np.testing.assert_allclose(t.state_covariance, C, atol=1e-12)


def test_skpf_update_position_is_the_seed_rule_and_calibration_its_regression():
    t = make_tracker("skpf", [0.3, -0.2], [[1.0, 0.2], [0.2, 0.5]], bias0_std_deg=8.0, scale0_std=0.1)
    t.predict(Step(0, 0.7, 40.0, 0.1, 5.0))
    x, P = t.state_mean, t.state_covariance
    seed = SKPFXYTracker(x[:2], P[:2, :2], q=0.0)
    R = np.array([[1.2, 0.1], [0.1, 0.9]])
    fix = Fix(1.5, 0.4, 0, R)
    seed.update(fix)
    t.update(fix)
    np.testing.assert_allclose(t.mean, seed.mean, atol=1e-12)  # the SKPF reweighting, as the seed
    np.testing.assert_allclose(t.state_mean[2:], x[2:] + P[2:, :2] @ np.linalg.solve(P[:2, :2], seed.mean - x[:2]),
                               atol=1e-12)
    K = P[:, :2] @ np.linalg.inv(P[:2, :2] + R)
    np.testing.assert_allclose(t.state_covariance, P - K @ (P[:2, :2] + R) @ K.T, atol=1e-12)


def test_pf_particles_carry_their_own_calibration():
    t = make_tracker("pf", [0, 0], np.eye(2) * 0.01, seed=4, n_particles=2000, q=0.0, bias0_std_deg=10.0,
                     scale0_std=0.1, bias_walk_deg=0.0, scale_walk=0.0)
    assert t.particles.shape == (2000, 4)
    assert np.std(np.degrees(t.particles[:, 2])) == pytest.approx(10.0, rel=0.1)
    assert np.std(t.particles[:, 3]) == pytest.approx(0.1, rel=0.1)
    before = t.particles.copy()
    t.predict(Step(0, 10.0, 0.0, length_std_m=1e-9, heading_std_deg=1e-9))
    # each particle moved 10·s_i along its own heading bias b_i
    moved = t.particles[:, :2] - before[:, :2]
    # (positions are kept on a grid of 256 values per column spanning the cloud: within half
    # its step, ≈ 2.5 cm here; b and s did not change)
    half = 0.5 * t._grid[1] + 1e-9
    np.testing.assert_allclose(moved[:, 0], 10 * before[:, 3] * np.sin(before[:, 2]), rtol=0, atol=half[0])
    np.testing.assert_allclose(moved[:, 1], 10 * before[:, 3] * np.cos(before[:, 2]), rtol=0, atol=half[1])
    assert half[0] < 0.03


@pytest.mark.parametrize("name", AUGMENTED)
def test_a_heading_bias_is_learned_on_a_simulated_walk(name):
    # The phone reports every heading 8° clockwise of the truth and 6 % long steps; with fixes
    # every 3 steps each filter learns b ≈ −8° and s ≈ 1/1.06 (its estimates over the second
    # half of the walk, averaged: the bias is a random walk, so each estimate wanders a little),
    # and beats its seed form.
    walk = simulate_walk(seed=5, legs=((0.0, 40), (90.0, 40), (180.0, 40)), heading_bias_deg=8.0,
                         heading_noise_deg=2.0, length_noise_m=0.02, fix_std_m=1.5, step_m=0.7)
    walk.events = [Step(e.t, e.length_m * 1.06, e.heading_deg) if isinstance(e, Step) else e for e in walk.events]
    t = make_tracker(name, walk.truth[0], np.eye(2) * 0.1, seed=1)
    learned, est = [], [t.mean]
    for e in walk.events:
        if isinstance(e, Step):
            t.predict(e)
            learned.append((t.heading_bias_deg, t.step_scale))
            est.append(t.mean)
        else:
            t.update(e)
            est[-1] = t.mean
    bias, scale = np.mean(learned[60:], axis=0)
    assert bias == pytest.approx(-8.0, abs=1.5), name
    assert scale == pytest.approx(1 / 1.06, abs=0.04), name
    seed = make_tracker(f"{name}-xy", walk.truth[0], np.eye(2) * 0.1, seed=1)
    seed_est = run_tracker(seed, walk)
    err = np.hypot(*(np.array(est) - walk.truth).T)[60:].mean()
    seed_err = np.hypot(*(seed_est - walk.truth).T)[60:].mean()
    assert err < 0.8 * seed_err, (name, err, seed_err)


@pytest.mark.parametrize("name", AUGMENTED)
def test_a_reset_keeps_what_was_learned(name):
    t = make_tracker(name, [0, 0], np.eye(2), seed=2)
    for k in range(20):
        t.predict(Step(k, 0.7, 0.0))
        t.update(Fix(0.2 * (k + 1), 0.7 * (k + 1), 0, np.eye(2)))
    b, s = t.heading_bias_deg, t.step_scale
    t.reset([5.0, 5.0], np.eye(2) * 2.0)
    np.testing.assert_allclose(t.mean, [5.0, 5.0], atol=0.3 if name == "pf" else 1e-12)
    assert t.heading_bias_deg == pytest.approx(b, abs=1.0 if name == "pf" else 1e-9)
    assert t.step_scale == pytest.approx(s, abs=0.02 if name == "pf" else 1e-12)


@pytest.mark.parametrize("name", AUGMENTED)
def test_inflate_grows_the_covariance_and_keeps_the_mean(name):
    t = make_tracker(name, [1.0, 2.0], np.eye(2), seed=2)
    t.predict(Step(0, 0.7, 30.0))
    m, P = t.mean, t.covariance
    t.inflate(4.0)
    # a PF keeps its particles as float16 offsets from their mean (well under 1 mm here)
    exact = not name.startswith("pf")
    np.testing.assert_allclose(t.mean, m, atol=1e-12 if exact else 1e-4)
    np.testing.assert_allclose(t.covariance, 4.0 * P, rtol=1e-6 if exact else 1e-3)


@pytest.mark.parametrize("name", AUGMENTED)
def test_the_augmented_state_survives_json_exactly(name):
    t = make_tracker(name, [0.5, -0.5], np.eye(2), seed=11)
    for k in range(10):
        t.predict(Step(k, 0.7, 10.0 * k))
        if k % 3 == 2:
            t.update(Fix(0.3 * k, 0.6 * k, 0, np.eye(2) * 2.0))
    restored = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    np.testing.assert_array_equal(restored.state_mean, t.state_mean)
    np.testing.assert_array_equal(restored.state_covariance, t.state_covariance)
    assert restored.to_dict() == t.to_dict()


SEED_CLASSES = {"ekf": EKFXYTracker, "ukf": UKFXYTracker, "pf": ParticleFilterXYTracker, "skpf": SKPFXYTracker}


@pytest.mark.parametrize("name", AUGMENTED)
def test_a_version_1_session_state_loads_as_the_seed_filter_it_started_with(name):
    """A session stored before the self-calibrating trackers (session state version 1, no
    tracker_params, tracker dict version 1 named "ekf"...) resumes with the two-state filter
    it was running, with the same future outputs."""
    est = SessionEstimator(f"{name}-xy", seed=4)
    est.start([1.0, 2.0], np.eye(2), 0, [], 0.0, "init")
    est.step(Step(1.0, 0.7, 45.0))
    old = json.loads(json.dumps(est.to_dict()))
    old["version"] = 1
    old["filter"] = name
    del old["tracker_params"]
    old["tracker"]["version"] = 1
    old["tracker"]["filter"] = name
    loaded = SessionEstimator.from_dict(old)
    assert type(loaded.tracker) is SEED_CLASSES[name] and loaded.filter == name
    assert loaded.tracker.to_dict()["filter"] == f"{name}-xy" and loaded.to_dict()["version"] == 2
    for e in (est, loaded):
        e.step(Step(2.0, 0.7, 50.0))
    np.testing.assert_array_equal(loaded.tracker.mean, est.tracker.mean)
    np.testing.assert_array_equal(loaded.tracker.covariance, est.tracker.covariance)


def test_a_version_1_kf_dict_still_loads_as_kf():
    d = make_tracker("kf", [0, 0], np.eye(2)).to_dict()
    restored = tracker_from_dict({**d, "version": 1})
    assert restored.name == "kf" and restored.to_dict() == d


# -- the walk's fix offset (a fix's ``shared_share``) ---------------------------------------------


def test_ekf_first_fix_with_a_walk_share_by_hand():
    # x0 = (0, 0, 0, 1), P0 = diag(1, 1, 0.01, 0.01). Fix (1, 0), R = I, ρ = 0.5: the state grows by
    # the offset o, prior N(0, 0.5·I); z = p + o + v, v ~ N(0, 0.5·I). S = P_pp + P_oo + 0.5·I = 2·I,
    # K_p = P_pp S⁻¹ = 0.5·I, K_o = P_oo S⁻¹ = 0.25·I: x = 0.5, oₓ = 0.25;
    # P_xx = 1 − 1/2 = 0.5, P_oo = 0.5 − 0.25/2 = 0.375, P_xo = −1·0.5/2 = −0.25 (per axis).
    off = make_tracker("ekf", [0, 0], np.eye(2), **STILL)  # by default (``walk_offset`` 0) the share is not used
    off.update(Fix(1.0, 0.0, 0, np.eye(2), shared_share=0.5))
    assert not off.has_offset and off.mean[0] == pytest.approx(0.5)
    t = make_tracker("ekf", [0, 0], np.eye(2), walk_offset=1, **STILL)
    assert not t.has_offset and t.fix_offset is None
    t.update(Fix(1.0, 0.0, 0, np.eye(2), shared_share=0.5))
    assert t.has_offset
    np.testing.assert_allclose(t.state_mean, [0.5, 0, 0, 1, 0.25, 0], atol=1e-12)
    P = t.state_covariance
    np.testing.assert_allclose(np.diag(P), [0.5, 0.5, 0.01, 0.01, 0.375, 0.375], atol=1e-12)
    np.testing.assert_allclose([P[0, 4], P[1, 5], P[0, 5]], [-0.25, -0.25, 0.0], atol=1e-12)
    # what it expects of the next such fix: p + o, with H P Hᵀ = P_pp + P_po + P_op + P_oo and (1 − ρ)·R
    e = t.fix_innovation(Fix(1.0, 0.0, 0, np.eye(2), shared_share=0.5))
    np.testing.assert_allclose(e.innovation, [0.25, 0.0], atol=1e-12)
    np.testing.assert_allclose(e.covariance, (0.5 - 0.5 + 0.375) * np.eye(2), atol=1e-12)
    assert e.noise_share == 0.5
    # a fix whose error is its own (a landmark snap: ρ 0) measures the position alone
    assert t.fix_innovation(Fix(1.0, 0.0, 0, np.eye(2), shared_share=0.0)).innovation[0] == pytest.approx(0.5)


def test_ekf_considers_the_walks_offset_by_hand():
    # ``walk_offset`` 2: the same first update as above for [x, y, b, s] and its cross-covariance with o
    # (x = 0.5, P_xx = 0.5, P_xo = −0.25 per axis), but o is not estimated: its mean stays 0 and
    # its covariance the prior 0.5·I (Schmidt–Kalman).
    t = make_tracker("ekf", [0, 0], np.eye(2), walk_offset=2, **STILL)
    t.update(Fix(1.0, 0.0, 0, np.eye(2), shared_share=0.5))
    np.testing.assert_allclose(t.state_mean, [0.5, 0, 0, 1, 0, 0], atol=1e-12)
    P = t.state_covariance
    np.testing.assert_allclose(np.diag(P), [0.5, 0.5, 0.01, 0.01, 0.5, 0.5], atol=1e-12)
    np.testing.assert_allclose([P[0, 4], P[1, 5], P[0, 5]], [-0.25, -0.25, 0.0], atol=1e-12)
    # the second fix at (1, 0): S = P_pp + P_po + P_op + P_oo + 0.5·I = 0.5 − 0.5 + 0.5 + 0.5 = 1;
    # K_p = (P_pp + P_po) S⁻¹ = 0.25: x = 0.5 + 0.25·0.5; P_xx = 0.5 − 0.25²·1, P_xo = −0.25 − 0.25·(−0.25 + 0.5)
    t.update(Fix(1.0, 0.0, 0, np.eye(2), shared_share=0.5))
    np.testing.assert_allclose(t.state_mean, [0.625, 0, 0, 1, 0, 0], atol=1e-12)
    P = t.state_covariance
    np.testing.assert_allclose([P[0, 0], P[0, 4], P[4, 4]], [0.4375, -0.3125, 0.5], atol=1e-12)


def test_inflating_an_ekf_that_considers_the_offset_widens_the_tracker_not_the_fixes():
    t = make_tracker("ekf", [0, 0], np.eye(2), walk_offset=2, **STILL)
    t.update(Fix(1.0, 0.0, 0, np.eye(2), shared_share=0.5))
    before = t.state_covariance
    t.inflate(4.0)
    P = t.state_covariance
    np.testing.assert_allclose(P[:4, :4], 4.0 * before[:4, :4], atol=1e-12)
    np.testing.assert_allclose(P[4:, 4:], 0.5 * np.eye(2), atol=1e-12)  # the prior, as before
    np.testing.assert_allclose(P[:4, 4:], 2.0 * before[:4, 4:], atol=1e-12)
    assert np.linalg.eigvalsh(P).min() > -1e-12


def _offset_walk(share: float | None, seed: int = 0, walk_offset: int = 1):
    """An EKF on a straight walk north with exact steps, fixes every 2 steps carrying one offset
    (3, −2) m for the whole walk plus white noise, declared as σ² = 8 m² with ``share``; the
    track's mean error and the mean NEES of its position."""
    rng = np.random.default_rng(seed)
    t = make_tracker("ekf", [0, 0], np.eye(2) * 0.01, walk_offset=walk_offset)
    errors, nees = [], []
    for k in range(1, 81):
        t.predict(Step(k, 0.7, 0.0, length_std_m=0.05, heading_std_deg=2.0))
        truth = np.array([0.0, 0.7 * k])
        if k % 2 == 0:
            z = truth + [3.0, -2.0] + np.sqrt(1.6) * rng.standard_normal(2)
            t.update(Fix(float(z[0]), float(z[1]), 0, np.eye(2) * 8.0, shared_share=share))
        e = t.mean - truth
        errors.append(float(np.hypot(*e)))
        nees.append(float(e @ np.linalg.solve(t.covariance, e)))
    return t, np.mean(errors), np.mean(nees)


def test_ekf_learns_the_walks_fix_offset_and_keeps_to_its_steps():
    """Fixes that share one offset along the walk: taken as independent they pull the track onto
    the offset; with their walk share the EKF learns the offset and keeps to its good steps."""
    t, err_offset, _ = _offset_walk(0.8)
    _, err_independent, _ = _offset_walk(None)
    np.testing.assert_allclose(t.fix_offset, [3.0, -2.0], atol=1.0)
    assert err_offset < 0.5 * err_independent, (err_offset, err_independent)


def test_ekf_considering_the_walks_offset_knows_what_its_fixes_cannot_tell():
    """The same walk, the offset considered (``walk_offset`` 2): never learned, so the track is
    not corrected as far, but the covariance keeps the part the fixes share — the EKF that takes
    them as independent believes their offset many times over (NEES far above 2)."""
    t, err_considered, nees_considered = _offset_walk(0.8, walk_offset=2)
    _, err_independent, nees_independent = _offset_walk(None)
    np.testing.assert_array_equal(t.fix_offset, [0.0, 0.0])
    assert err_considered < err_independent, (err_considered, err_independent)
    assert nees_independent > 10.0 and nees_considered < 4.0, (nees_independent, nees_considered)


@pytest.mark.parametrize("walk_offset", [1, 2])
def test_ekf_with_the_walk_offset_survives_json_exactly_and_a_reset_drops_it(walk_offset):
    t, _, _ = _offset_walk(0.8, walk_offset=walk_offset)
    restored = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    assert restored.has_offset
    for tracker in (t, restored):
        tracker.predict(Step(99, 0.7, 5.0))
        tracker.update(Fix(2.0, 57.0, 0, np.eye(2) * 8.0, shared_share=0.8))
        tracker.update_range([1.0, 57.0], 1.5, 0.5)
    np.testing.assert_array_equal(restored.state_mean, t.state_mean)
    np.testing.assert_array_equal(restored.state_covariance, t.state_covariance)
    b = t.heading_bias_deg
    t.reset([0.0, 0.0], np.eye(2))
    assert not t.has_offset and t.state_mean.shape == (4,) and t.heading_bias_deg == pytest.approx(b)
