"""On-phone PDR on synthetic walks with known steps."""

import numpy as np
import pytest

from client_sim.imu import ImuParams, synthesize_imu
from client_sim.pdr import PdrConfig, run_pdr
from client_sim.pdr.step_detection import detect_steps_two_threshold, find_step_peaks
from client_sim.pdr.step_length import calibrate_quadratic, calibrate_weinberg, quadratic, weinberg
from client_sim.walker import Gait, walk_route, wrap_deg
from client_sim.world import corridor_loop

CLEAN = ImuParams(weinberg_k=0.40, mag_disturbance_ut=0.0)  # a person whose true k is not the default


def _walk(route, seed, gait: Gait | None = None):
    walk = walk_route(route, gait or Gait(), np.random.default_rng(seed))
    imu = synthesize_imu(walk, np.random.default_rng(seed + 100), CLEAN)
    return walk, imu


def test_step_count_is_exact_on_synthetic_walks():
    w = corridor_loop()
    for seed, route in enumerate(w.routes[:2]):
        walk, imu = _walk(route, seed, Gait(step_freq_hz=1.6 + 0.3 * seed))
        assert len(find_step_peaks(imu.t, imu.acc)) == walk.n_steps


def test_weinberg_length_after_calibration_within_5_percent():
    straight = [(0, 0, 0), (0, 20, 0)]
    _, cal_imu = _walk(straight, 1)
    ev = find_step_peaks(cal_imu.t, cal_imu.acc)
    k = calibrate_weinberg(ev.a_max, ev.a_min, 20.0)  # "walk 20 m" calibration
    assert k == pytest.approx(0.40, rel=0.05)
    walk, imu = _walk(corridor_loop().routes[0], 2)
    steps, _ = run_pdr(imu, PdrConfig(weinberg_k=k))
    est = np.array([s.length_m for s in steps])
    true = walk.length_m[1:]
    assert abs(est.sum() / true.sum() - 1) < 0.05
    assert np.mean(np.abs(est / true - 1)) < 0.05


def test_heading_within_5_degrees_without_magnetic_disturbance():
    walk, imu = _walk(corridor_loop().routes[0], 3)
    steps, _ = run_pdr(imu, PdrConfig())
    assert len(steps) == walk.n_steps
    err = np.abs(wrap_deg(np.array([s.heading_deg for s in steps]) - walk.heading_deg[1:]))
    assert np.mean(err) < 5.0
    assert np.percentile(err, 95) < 5.0


def test_quaternion_ekf_heading_tracks_turns():
    walk, imu = _walk(corridor_loop().routes[0], 4)
    steps, _ = run_pdr(imu, PdrConfig(heading="qekf"), initial_heading_deg=float(walk.heading_deg[0]))
    err = np.abs(wrap_deg(np.array([s.heading_deg for s in steps]) - walk.heading_deg[1:]))
    assert np.mean(err) < 5.0


def test_magnetic_disturbance_is_what_breaks_the_compass():
    w = corridor_loop()
    walk = walk_route(w.routes[0], Gait(), np.random.default_rng(5))
    errs = []
    for dist in (0.0, 15.0):
        imu = synthesize_imu(walk, np.random.default_rng(6), ImuParams(mag_disturbance_ut=dist), field_seed=1)
        steps, _ = run_pdr(imu)
        errs.append(np.mean(np.abs(wrap_deg(np.array([s.heading_deg for s in steps]) - walk.heading_deg[1:]))))
    assert errs[0] < 3.0 < errs[1]


def test_two_threshold_rule():
    t = np.arange(0, 5, 0.01)
    a = 2.0 * np.sin(2 * np.pi * 1.8 * t)  # 9 cycles of +2/−2 m/s²
    assert len(detect_steps_two_threshold(t, a)) == 9
    assert len(detect_steps_two_threshold(t, 0.9 * np.sin(2 * np.pi * 1.8 * t))) == 0  # never above +1.0


def test_quadratic_step_length_calibration():
    a = np.linspace(1, 4, 20)
    true = 0.3 + 0.1 * a + 0.01 * a * a
    coeffs = calibrate_quadratic(a, true)
    assert np.allclose(quadratic(a, coeffs), true)
    assert weinberg(np.array([3.0]), np.array([-3.0]), 0.5)[0] == pytest.approx(0.5 * 6 ** 0.25)


def test_same_seed_same_walk_and_sensors():
    w = corridor_loop()
    a_walk, a_imu = _walk(w.routes[0], 9)
    b_walk, b_imu = _walk(w.routes[0], 9)
    assert np.array_equal(a_walk.t, b_walk.t) and np.array_equal(a_imu.acc, b_imu.acc)
    c_walk, _ = _walk(w.routes[0], 10)
    assert not np.array_equal(a_walk.t, c_walk.t)
