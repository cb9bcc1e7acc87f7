"""KF and fuzzy KF pinned to hand-computed one-step results and to filterpy."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from server.estimation.tracking import make_tracker
from server.estimation.types import Area, Fix, Step


def fix(x, y, cov=None):
    return Fix(x, y, 0, np.eye(2) if cov is None else np.asarray(cov, float))


def test_kf_one_step_by_hand():
    # x0 = (0, 0), P0 = I, Q = 0.5·I, R = 1·I.
    # Step 1 m at heading 90° (east): x⁻ = (1, 0), P⁻ = 1.5·I.
    # Fix z = (2, 1): K = 1.5 / (1.5 + 1) = 0.6, x⁺ = (1 + 0.6·1, 0 + 0.6·1) = (1.6, 0.6),
    # P⁺ = (1 − 0.6)·1.5 = 0.6·I.
    t = make_tracker("kf", [0, 0], np.eye(2), q=0.5, r=1.0)
    t.predict(Step(0.0, 1.0, 90.0))
    np.testing.assert_allclose(t.mean, [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(t.covariance, 1.5 * np.eye(2), atol=1e-12)
    t.update(fix(2.0, 1.0))
    np.testing.assert_allclose(t.mean, [1.6, 0.6], atol=1e-12)
    np.testing.assert_allclose(t.covariance, 0.6 * np.eye(2), atol=1e-12)


def test_kf_ignores_fix_covariance():
    a = make_tracker("kf", [0, 0], np.eye(2), q=0.5, r=1.0)
    b = make_tracker("kf", [0, 0], np.eye(2), q=0.5, r=1.0)
    a.update(fix(2.0, 1.0, np.eye(2) * 0.01))
    b.update(fix(2.0, 1.0, np.eye(2) * 100.0))
    np.testing.assert_array_equal(a.mean, b.mean)


def test_kf_matches_filterpy_configured_by_hand():
    rng = np.random.default_rng(3)
    ref = KalmanFilter(dim_x=2, dim_z=2)
    ref.x = np.array([[1.0], [2.0]])
    ref.P = np.diag([2.0, 0.5])
    ref.F = np.eye(2)
    ref.H = np.eye(2)
    ref.Q = np.eye(2) * 0.3
    ref.R = np.eye(2) * 2.5
    t = make_tracker("kf", [1.0, 2.0], np.diag([2.0, 0.5]), q=0.3, r=2.5)
    for k in range(20):
        step = Step(k, 0.6 + 0.1 * rng.random(), 360 * rng.random())
        d = np.array([[step.length_m * np.sin(np.radians(step.heading_deg))],
                      [step.length_m * np.cos(np.radians(step.heading_deg))]])
        ref.x = ref.x + d  # control input applied by hand: x⁻ = F x + u
        ref.predict()
        t.predict(step)
        if k % 3 == 0:
            z = rng.normal(size=2) * 2
            ref.update(z.reshape(2, 1))
            t.update(fix(*z))
        np.testing.assert_allclose(t.mean, ref.x.ravel(), atol=1e-10)
        np.testing.assert_allclose(t.covariance, ref.P, atol=1e-10)


@pytest.mark.parametrize(
    "z, expected_r",
    [((0.5, 0.0), 0.675), ((1.5, 0.0), 1.125), ((0.0, 2.5), 1.575), ((1.2, 1.2), 1.125)],
)
def test_fkf_switches_r_by_residual(z, expected_r):
    # DESIGN's literal numbers (scale="none": thresholds in m, levels in m²).
    # x0 = (0, 0), P0 = I; no step, so P⁻ = I and the residual is ‖z‖.
    # K = 1 / (1 + r), x⁺ = K·z, P⁺ = (1 − K)·I = r/(1 + r)·I.
    t = make_tracker("fkf", [0, 0], np.eye(2), scale="none")
    t.update(fix(*z, cov=np.eye(2) * 50.0))  # its own covariance is not used
    assert t.last_r == expected_r
    k = 1.0 / (1.0 + expected_r)
    np.testing.assert_allclose(t.mean, k * np.asarray(z), atol=1e-12)
    np.testing.assert_allclose(t.covariance, (1 - k) * np.eye(2), atol=1e-12)


def test_fkf_process_noise_is_0225_per_step():
    t = make_tracker("fkf", [0, 0], np.eye(2))
    t.predict(Step(0, 0.7, 0))
    t.predict(Step(1, 0.7, 0))
    np.testing.assert_allclose(t.covariance, (1 + 2 * 0.225) * np.eye(2), atol=1e-12)


def test_fkf_search_region_is_within_9m_of_the_estimate():
    t = make_tracker("fkf", [3.0, -4.0], np.eye(2))
    assert t.search_region() == Area(3.0, -4.0, 9.0)
    t.predict(Step(0, 1.0, 90.0))
    area = t.search_region()
    assert area is not None and (area.x, area.y, area.radius_m) == pytest.approx((4.0, -4.0, 9.0))
    assert make_tracker("kf", [0, 0], np.eye(2)).search_region() is None


def test_fkf_pdr_track_reset_every_10_steps():
    t = make_tracker("fkf", [0, 0], np.eye(2))
    for k in range(9):
        t.predict(Step(k, 1.0, 0.0))
    t.update(fix(3.0, 9.0))  # pulls the fused estimate east, the PDR track stays
    np.testing.assert_allclose(t.pdr_position, [0.0, 9.0])
    assert not np.allclose(t.pdr_position, t.mean)
    t.predict(Step(9, 1.0, 0.0))  # 10th step: PDR re-anchored on the estimate
    np.testing.assert_allclose(t.pdr_position, t.mean)
    assert t.pdr_position[0] > 1.0


@pytest.mark.parametrize(
    "z, level",
    # fix covariance diag(3, 5): σ = sqrt(trace/2) = sqrt(4) = 2 m. Residual ‖z‖ / σ:
    # 0.5 → < 1σ → 0.675·σ² = 2.7; 1.5 → < 2σ → 1.125·4 = 4.5; 2.5 → ≥ 2σ → 1.575·4 = 6.3.
    [((1.0, 0.0), 2.7), ((3.0, 0.0), 4.5), ((0.0, 5.0), 6.3), ((2.4, 3.2), 6.3), ((2.0, 3.2), 4.5)],
)
def test_fkf_scales_thresholds_and_r_to_the_fix_spread(z, level):
    # Default scale="fix". x0 = (0, 0), P0 = I, no step: K = 1/(1 + r), P⁺ = r/(1 + r)·I.
    t = make_tracker("fkf", [0, 0], np.eye(2))
    assert t.fix_sigma(fix(0, 0, cov=np.diag([3.0, 5.0]))) == pytest.approx(2.0)
    t.update(fix(*z, cov=np.diag([3.0, 5.0])))
    assert t.last_r == pytest.approx(level, abs=1e-12)
    k = 1.0 / (1.0 + level)
    np.testing.assert_allclose(t.mean, k * np.asarray(z), atol=1e-12)
    np.testing.assert_allclose(t.covariance, (1 - k) * np.eye(2), atol=1e-12)


def test_fkf_scale_fix_with_unit_fix_is_design_literal():
    # σ_fix = 1 m: the scaled rule reduces to DESIGN's absolute numbers.
    for z in [(0.5, 0.0), (1.5, 0.0), (0.0, 2.5)]:
        a = make_tracker("fkf", [0, 0], np.eye(2))
        b = make_tracker("fkf", [0, 0], np.eye(2), scale="none")
        a.update(fix(*z))
        b.update(fix(*z))
        assert a.last_r == pytest.approx(b.last_r, abs=1e-12)
        np.testing.assert_allclose(a.mean, b.mean, atol=1e-12)
    with pytest.raises(ValueError):
        make_tracker("fkf", [0, 0], np.eye(2), scale="metres")


def test_fkf_releases_the_box_after_a_lost_track_and_restores_it():
    # σ_fix = 1 m; a residual ≥ 2σ counts as large. lost_after = 3 consecutive large ones.
    t = make_tracker("fkf", [0, 0], np.eye(2) * 0.01, q=0.0)
    assert t.search_region() == Area(0.0, 0.0, 9.0)
    t.update(fix(8.0, 0.0))
    t.update(fix(8.0, 0.0))
    assert t.large_residuals == 2 and not t.lost and t.search_region() is not None
    t.update(fix(0.5, 0.0))  # a small residual: the count starts again
    assert t.large_residuals == 0
    for _ in range(3):
        assert t.search_region() is not None
        t.update(fix(8.0, 0.0))
    assert t.lost and t.search_region() is None  # unrestricted fixes may re-acquire the track
    # the state survives a store/load
    from server.estimation.tracking import tracker_from_dict

    assert tracker_from_dict(t.to_dict()).search_region() is None
    x = t.mean[0]
    t.update(fix(x + 0.3, 0.0))  # a fix that agrees again: box back, around the estimate
    assert not t.lost
    region = t.search_region()
    assert region is not None and region.radius_m == 9.0 and region.x == pytest.approx(t.mean[0])


def test_fkf_lost_after_zero_keeps_the_box():
    t = make_tracker("fkf", [0, 0], np.eye(2) * 0.01, lost_after=0)
    for _ in range(10):
        t.update(fix(8.0, 0.0))
    assert t.search_region() is not None
