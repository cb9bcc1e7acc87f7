"""Landmark hysteresis, Tukey filter, floor hysteresis, crowdsourcing, path loss."""

import copy
import json
import math

import numpy as np
import pytest

from server.estimation.radio import range_and_std, range_from_rss
from server.estimation.tracking import (
    FloorTracker,
    LandmarkCorrector,
    apply_snap,
    find_merge_target,
    gate,
    make_crowd_point,
    make_tracker,
    merge_points,
)
from server.estimation.tracking.landmarks import ScalarKalman, TukeyFilter
from server.estimation.types import CrowdPoint

BEACON = "ble:b1"


def _feed(lc, value, n):
    snaps = []
    for _ in range(n):
        snaps += lc.observe({BEACON: value, "wifi:ap": -40.0})  # unknown ids are ignored
    return snaps


def test_landmark_snaps_once_and_again_only_after_leaving():
    lc = LandmarkCorrector({BEACON: (5.0, 6.0)})
    assert _feed(lc, -70.0, 10) == []
    snaps = _feed(lc, -45.0, 100)  # enters the strong zone (> −52): one snap
    assert len(snaps) == 1 and snaps[0].beacon_id == BEACON
    assert (snaps[0].x, snaps[0].y) == (5.0, 6.0) and snaps[0].rss_dbm > -52
    assert _feed(lc, -58.0, 100) == []  # weaker, but not below −65: still disarmed
    assert lc.filtered_rss(BEACON) > -65
    assert _feed(lc, -45.0, 100) == []  # back in the zone without having left: no snap
    assert _feed(lc, -75.0, 100) == []  # leaves (< −65): re-armed
    assert lc.filtered_rss(BEACON) < -65
    assert len(_feed(lc, -45.0, 100)) == 1  # snaps again


def test_landmark_round_trip_and_apply_snap():
    lc = LandmarkCorrector({BEACON: (5.0, 6.0)})
    _feed(lc, -70.0, 10)
    restored = LandmarkCorrector.from_dict(json.loads(json.dumps(lc.to_dict())))
    a, b = _feed(lc, -45.0, 60), _feed(restored, -45.0, 60)
    assert a == b and len(a) == 1
    t = make_tracker("ekf", [0, 0], np.eye(2) * 4)
    apply_snap(t, a[0])
    np.testing.assert_array_equal(t.mean, [5.0, 6.0])
    np.testing.assert_array_equal(t.covariance, np.eye(2))


def test_tukey_rejects_outlier_and_kalman_ignores_it():
    tk = TukeyFilter(window=10)
    for v in [-60, -61, -59, -60, -62, -60, -61]:
        assert tk.accept(v)
    assert not tk.accept(-90.0)
    assert tk.accept(-60.5)
    lc = LandmarkCorrector({BEACON: (0, 0)})
    _feed(lc, -60.0, 8)
    level = lc.filtered_rss(BEACON)
    lc.observe({BEACON: -20.0})  # a single spike would otherwise snap
    assert lc.filtered_rss(BEACON) == level


def test_scalar_kalman_by_hand():
    # x0 = −60 (first sample, p = R = 1.5); z = −58: p⁻ = 1.515, K = 1.515/3.015,
    # x = −60 + K·2.
    kf = ScalarKalman(q=0.015, r=1.5)
    kf.update(-60.0)
    k = 1.515 / 3.015
    assert kf.update(-58.0) == pytest.approx(-60 + 2 * k)
    assert kf.p == pytest.approx((1 - k) * 1.515)


def test_floor_hysteresis():
    ft = FloorTracker(0, required=3)
    assert [ft.observe(f) for f in (1, 1)] == [False, False] and ft.floor == 0
    ft.observe(0)  # agreement broken
    assert [ft.observe(f) for f in (1, 1)] == [False, False] and ft.floor == 0
    ft2 = FloorTracker.from_dict(json.loads(json.dumps(ft.to_dict())))
    assert ft2.observe(1) is True and ft2.floor == 1
    for f in (2, 3, 2, 3, 2, 3):  # flickering never settles
        assert ft2.observe(f) is False
    assert ft2.floor == 1


def test_crowd_gate():
    ok = {"estimate_mean": [1, 1], "estimate_cov": np.eye(2) * 0.5, "fix_mean": [2, 1], "rss": {"a": -60, "b": -70, "c": -80}}
    assert gate(**ok)
    assert not gate(**{**ok, "estimate_cov": np.eye(2) * 1.5})  # trace 3 > 2
    assert not gate(**{**ok, "fix_mean": [5, 1]})  # 4 m apart > 3
    assert not gate(**{**ok, "rss": {"a": -60}})
    assert "trace" in gate(**{**ok, "estimate_cov": np.eye(2) * 5}).reason
    assert gate(**ok, level=(0, 1), fix_level=(0, 1), heard_level=(0, 1))
    assert not gate(**ok, level=(0, 1), fix_level=(0, 2))
    refused = gate(**ok, level=(0, 1), fix_level=(0, 1), heard_level=(0, 0))
    assert not refused and "strongest positioned transmitter" in refused.reason


def test_crowd_merge_within_1m_else_insert():
    stored = [make_crowd_point(0.0, 0.0, 0, {"a": -60.0}), make_crowd_point(10.0, 0.0, 0, {"a": -80.0})]
    before = copy.deepcopy(stored)
    new = make_crowd_point(0.5, 0.5, 0, {"a": -70.0, "b": -80.0})  # 0.71 m from the first
    assert find_merge_target(stored, new) == 0
    p = merge_points(stored[0], new)
    assert (p.x, p.y, p.count) == (0.25, 0.25, 2)
    assert p.rss == {"a": -65.0, "b": -80.0} and p.counts == {"a": 2, "b": 1}
    assert stored == before  # pure
    p2 = merge_points(p, make_crowd_point(0.25, 0.25, 0, {"a": -62.0}))
    assert p2.rss["a"] == pytest.approx((-65.0 * 2 - 62.0) / 3) and p2.counts["a"] == 3
    assert find_merge_target([p, stored[1]], make_crowd_point(1.5, 0.0, 0, {"a": -60.0})) is None
    assert find_merge_target([p, stored[1]], make_crowd_point(0.0, 0.0, 1, {"a": -60.0})) is None  # other floor


def test_a_stored_point_without_reading_counts_weighs_each_reading_by_its_point_count():
    stored = CrowdPoint(0.0, 0.0, 0, {"a": -60.0}, count=3)  # as read back from the database
    p = merge_points(stored, make_crowd_point(0.0, 0.0, 0, {"a": -80.0}))
    assert p.rss["a"] == pytest.approx(-65.0) and p.count == 4


def test_path_loss_range():
    # RSS = R0 − 10γ log10 d with R0 = −59, γ = 2: −79 dBm ↔ 10 m.
    assert range_from_rss(-59.0, -59.0, 2.0) == pytest.approx(1.0)
    d, s = range_and_std(-79.0, -59.0, 2.0, rss_std_db=4.0)
    assert d == pytest.approx(10.0)
    assert s == pytest.approx(10.0 * math.log(10) * 4.0 / 20.0)  # ≈ 4.6 m


def test_fix_cov_entries_equal_fix_cov():
    from server.estimation.tracking.base import fix_cov, fix_cov_entries

    for cov in ([[2.0, 0.3], [0.5, 1.0]], np.diag([3.0, 5.0]), np.zeros((2, 2)), 0.5, np.diag([1e-4, 2.0])):
        R = fix_cov(cov)
        assert fix_cov_entries(cov) == pytest.approx((R[0, 0], R[0, 1], R[1, 1]), abs=1e-15)
    for bad in (np.full((2, 2), np.nan), [[1.0, 0.0], [0.0, np.inf]], np.eye(3)):
        with pytest.raises(ValueError):
            fix_cov_entries(bad)


def test_fix_cov_bounds_both_axes_and_keeps_them():
    from server.estimation.tracking.base import MAX_FIX_VAR_M2, MIN_FIX_VAR_M2, fix_cov, fix_cov_entries

    c, s = np.cos(0.4), np.sin(0.4)
    axes = np.array([[c, -s], [s, c]])
    wide = axes @ np.diag([1e12, 4.0]) @ axes.T  # σ 1000 km along one axis, 2 m along the other
    w, v = np.linalg.eigh(fix_cov(wide))
    assert w == pytest.approx([4.0, MAX_FIX_VAR_M2], rel=1e-4)  # (4 m² within a 10¹² m² matrix's precision)
    assert abs(v[:, 1] @ axes[:, 0]) == pytest.approx(1.0)
    assert fix_cov_entries(wide) == pytest.approx(tuple(fix_cov(wide)[[0, 0, 1], [0, 1, 1]]))
    assert np.linalg.eigvalsh(fix_cov(np.diag([0.0, 1e9])))[[0, -1]] == pytest.approx([MIN_FIX_VAR_M2, MAX_FIX_VAR_M2])
