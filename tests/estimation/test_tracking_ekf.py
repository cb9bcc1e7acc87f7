"""EKF pinned to hand-computed results: Jacobian-mapped step noise, fix with its own
covariance, beacon range (only within 3 m) and the wall-side constraint."""

import math

import numpy as np

from server.estimation.tracking import make_tracker
from server.estimation.types import Fix, Step


def test_ekf_one_step_by_hand():
    # x0 = (0, 0), P0 = I, q = 0. Step d = 2 m, h = 0°, σd = 0.1 m, σh = 0.1 rad.
    # J = [[sin h, d cos h], [cos h, −d sin h]] = [[0, 2], [1, 0]],
    # J diag(0.01, 0.01) Jᵀ = [[4·0.01, 0], [0, 0.01]] = diag(0.04, 0.01).
    # x⁻ = (0, 2), P⁻ = diag(1.04, 1.01).
    t = make_tracker("ekf-xy", [0, 0], np.eye(2), q=0.0)
    t.predict(Step(0, 2.0, 0.0, length_std_m=0.1, heading_std_deg=math.degrees(0.1)))
    np.testing.assert_allclose(t.mean, [0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(t.covariance, np.diag([1.04, 1.01]), atol=1e-12)
    # Fix z = (1, 3) with R = diag(0.96, 0.99) (the fix's covariance is R):
    # S = diag(2.0, 2.0), K = diag(0.52, 0.505), x⁺ = (0.52, 2.505),
    # P⁺ = diag(1.04·0.48, 1.01·0.495) = diag(0.4992, 0.49995).
    t.update(Fix(1.0, 3.0, 0, np.diag([0.96, 0.99])))
    np.testing.assert_allclose(t.mean, [0.52, 2.505], atol=1e-12)
    np.testing.assert_allclose(t.covariance, np.diag([0.4992, 0.49995]), atol=1e-12)


def test_ekf_heading_noise_grows_cross_track_variance_with_step_length():
    short = make_tracker("ekf-xy", [0, 0], np.eye(2) * 0.01, q=0.0)
    long = make_tracker("ekf-xy", [0, 0], np.eye(2) * 0.01, q=0.0)
    short.predict(Step(0, 0.5, 90.0, length_std_m=0.0, heading_std_deg=10.0))
    long.predict(Step(0, 1.5, 90.0, length_std_m=0.0, heading_std_deg=10.0))
    # heading 90°: cross-track is y; variance d²σh² grows 9× from 0.5 m to 1.5 m
    sigma_h = math.radians(10.0)
    assert np.isclose(short.covariance[1, 1], 0.01 + 0.25 * sigma_h**2)
    assert np.isclose(long.covariance[1, 1], 0.01 + 2.25 * sigma_h**2)
    assert np.isclose(long.covariance[0, 0], 0.01)


def test_ekf_range_update_by_hand():
    # x⁻ = (0, 0), P = I, beacon (2, 0), r = 1.5 m, σr = 0.5 m, in log-range:
    # z = ln 1.5, R = (0.5/1.5)² = 1/9; h = ln 2, H = (x − b)ᵀ/‖x − b‖² = (−0.5, 0),
    # S = 0.25 + 1/9 = 13/36, K = PHᵀ/S = (−18/13, 0), y = ln(1.5/2),
    # x⁺ = (−18/13·ln 0.75, 0), P⁺ = diag(1 − 9/13, 1).
    t = make_tracker("ekf-xy", [0, 0], np.eye(2))
    assert t.update_range([2.0, 0.0], 1.5, 0.5) is True
    np.testing.assert_allclose(t.mean, [-18 / 13 * math.log(0.75), 0.0], atol=1e-12)
    np.testing.assert_allclose(t.covariance, np.diag([4 / 13, 1.0]), atol=1e-12)


def test_ekf_range_ignored_beyond_3m():
    t = make_tracker("ekf-xy", [0, 0], np.eye(2))
    assert t.update_range([4.0, 0.0], 3.01, 0.5) is False
    np.testing.assert_array_equal(t.mean, [0.0, 0.0])
    np.testing.assert_array_equal(t.covariance, np.eye(2))
    assert t.update_range([4.0, 0.0], 2.99, 0.5) is True
    assert t.mean[0] > 0.5


def _crossing_setup():
    # Beacon at the origin on a wall along the x axis; the prior is just north of the
    # wall with a strongly correlated P, so the linearised range update lands south.
    P = np.array([[1.0, 0.95], [0.95, 1.0]])
    return make_tracker("ekf-xy", [1.0, 0.2], P), [-5.0, 0.0, 5.0, 0.0]


def test_ekf_wall_side_constraint_keeps_position_on_beacon_side():
    free, wall = _crossing_setup()
    free.update_range([0.0, 0.0], 0.2, 0.1)
    assert free.mean[1] < 0  # precondition: without the constraint it crosses
    held, _ = _crossing_setup()
    held.update_range([0.0, 0.0], 0.2, 0.1, on_wall=wall)
    assert held.mean[1] > 0
    np.testing.assert_allclose(held.mean, [free.mean[0], 0.05], atol=1e-12)  # foot + margin


def test_ekf_wall_side_explicit_side():
    t = make_tracker("ekf-xy", [1.0, 0.2], np.eye(2))
    # The beacon faces south (right of the directed wall); the estimate is moved there.
    t.update_range([0.0, 0.0], 1.0, 0.3, on_wall={"wall": [-5, 0, 5, 0], "side": -1})
    assert t.mean[1] < 0
