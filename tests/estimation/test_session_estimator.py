"""SessionEstimator: stored and restored between any two inputs, it gives exactly what an
uninterrupted estimator gives (so a session may move between server processes)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from server.estimation.session import SessionEstimator, multilateration_fix, time_order
from server.estimation.tracking import tracker_names
from server.estimation.tracking.base import TRACKERS
from server.estimation.types import Beacon, Estimate, Fix, NoFix, Scan, SiteMap, Step

BEACONS = {
    "ble:b1": Beacon("ble:b1", 5.0, 0.0, 0, -59.0, 2.0),
    "wifi:a": Beacon("wifi:a", 0.0, 0.0, 0),
    "wifi:b": Beacon("wifi:b", 10.0, 0.0, 0),
    "wifi:c": Beacon("wifi:c", 0.0, 10.0, 0),
}


def inputs():
    rng = np.random.default_rng(1)
    out = []
    for i in range(30):
        out.append(("step", Step(t=i * 0.5, length_m=0.7, heading_deg=90.0)))
        if i % 3 == 2:
            x = 0.7 * (i + 1)
            fix = Fix(x + rng.normal(0, 0.5), rng.normal(0, 0.5), 0, np.eye(2) * 0.5)
            rss = {"ble:b1": -59.0 - 20 * np.log10(max(abs(x - 5.0), 0.5)), "wifi:a": -60.0}
            out.append(("scan", (Scan(t=i * 0.5 + 0.1, rss=rss), fix)))
    return out


SITE = SiteMap(BEACONS)
EMPTY = SiteMap()


def feed(est: SessionEstimator, items) -> list[Estimate | None]:
    out = []
    for kind, item in items:
        if kind == "step":
            out.append(est.step(item))
        else:
            scan, fix = item
            out.append(est.scan(scan, fix, SITE).estimate)
    return out


@pytest.mark.parametrize("name", tracker_names())
def test_restored_estimator_continues_exactly(name):
    items = inputs()
    straight = SessionEstimator(name, seed=7)
    straight.start([0.0, 0.0], None, 0, [], None, "init")
    expected = feed(straight, items)

    resumed = SessionEstimator(name, seed=7)
    resumed.start([0.0, 0.0], None, 0, [], None, "init")
    got = []
    for k in range(0, len(items), 4):  # store (through JSON) and restore every 4 inputs
        resumed = SessionEstimator.from_dict(json.loads(json.dumps(resumed.to_dict())))
        got += feed(resumed, items[k:k + 4])
    assert got == expected
    assert expected[-1].x == pytest.approx(0.7 * 30, abs=3.0)


def test_steps_before_the_first_fix_are_dropped_and_the_first_scan_starts():
    est = SessionEstimator("kf", seed=1)
    assert est.step(Step(0.0, 0.7, 0.0)) is None and est.estimate is None
    e = est.scan(Scan(1.0, {"wifi:a": -50.0}), Fix(3.0, 4.0, 2, np.eye(2)), EMPTY).estimate
    assert e.source == "scan" and (e.x, e.y, e.floor) == (3.0, 4.0, 2)


def test_floor_change_needs_three_fixes_and_loads_the_new_walls():
    est = SessionEstimator("pf", seed=1)
    est.start([0.0, 0.0], None, 0, [], None, "init")
    site = SiteMap(walls={(0, 0): [], (0, 1): [[-1.0, 5.0, 1.0, 5.0]]})
    floors = []
    for i in range(3):
        e = est.scan(Scan(float(i), {"wifi:x": -50.0}), Fix(2.0, 2.0, 1, np.eye(2)), site).estimate
        floors.append(e.floor)
    assert floors == [0, 0, 1]
    assert est.tracker.walls.tolist() == [[-1.0, 5.0, 1.0, 5.0]]


def test_landmark_snap_moves_onto_the_beacon():
    est = SessionEstimator("kf", seed=1)
    est.start([20.0, 20.0], None, 0, [], None, "init")
    far = Fix(20.0, 20.0, 0, np.eye(2) * 100.0)
    e = est.scan(Scan(0.0, {"ble:b1": -40.0}), far, SITE).estimate
    assert (e.x, e.y) == pytest.approx((5.0, 0.0))


LANDMARK = SiteMap({"ble:mark": Beacon("ble:mark", 5.0, 0.0, 0)})  # a position, no radio model: no range update
OTHER_FLOOR = Fix(0.0, 0.0, 1, np.eye(2))  # a fix on an unconfirmed floor moves nothing
AUGMENTED = [n for n in tracker_names() if TRACKERS[n].augmented]
SEED_FORMS = [n for n in tracker_names() if n not in AUGMENTED]


def _snap_from(name: str, x: float, y: float) -> tuple[SessionEstimator, np.ndarray, np.ndarray, str | None]:
    """A session at (x, y) with σ = 1 m hearing the landmark at (5, 0) in its strong zone: (session, mean and
    covariance before the scan, why the snap was refused)."""
    est = SessionEstimator(name, seed=2)
    est.start([x, y], np.eye(2), 0, [], None, "init")
    assert est.tracker is not None
    before = (est.tracker.mean.copy(), est.tracker.covariance.copy())
    r = est.scan(Scan(0.0, {"ble:mark": -40.0}), OTHER_FLOOR, LANDMARK)
    return est, *before, r.refused_snap


@pytest.mark.parametrize("name", AUGMENTED)
def test_a_plausible_landmark_snap_is_fused_as_a_measurement(name):
    est, mean, cov, refused = _snap_from(name, 4.0, 0.5)
    assert refused is None
    after = est.tracker.mean
    beacon = np.array([5.0, 0.0])
    # between the estimate and the beacon (a Kalman update of two σ = 1 m positions: about halfway), not onto it
    assert 0.2 < np.linalg.norm(after - beacon) < 0.8 * np.linalg.norm(mean - beacon)
    assert np.trace(est.tracker.covariance) < 0.8 * np.trace(cov)


@pytest.mark.parametrize("name", AUGMENTED)
def test_a_landmark_snap_far_from_a_confident_estimate_is_refused(name):
    est, mean, cov, refused = _snap_from(name, 11.5, 0.0)  # 6.5 m off: d² ≈ 21 > 13.82
    assert np.array_equal(est.tracker.mean, mean) and np.array_equal(est.tracker.covariance, cov)
    distance = np.hypot(*(np.array([5.0, 0.0]) - mean))  # (a PF's mean is its particles')
    assert refused is not None and refused.startswith(f"landmark snap to ble:mark {distance:.1f} m from the estimate")


@pytest.mark.parametrize("name", SEED_FORMS)
def test_a_seed_form_restarts_on_the_landmark_wherever_it_is(name):
    est, _, _, refused = _snap_from(name, 11.5, 0.0)
    assert est.tracker.mean == pytest.approx([5.0, 0.0], abs=0.3) and refused is None


def _scan_at(est: SessionEstimator, t: float, x: float, y: float) -> tuple[Estimate, str | None]:
    r = est.scan(Scan(t, {"wifi:a": -60.0}), Fix(x, y, 0, np.eye(2) * 1.0), EMPTY)
    return r.estimate, r.refused_fix


@pytest.mark.parametrize("name", tracker_names())
def test_an_outlier_fix_is_refused_and_moves_nothing(name):
    est = SessionEstimator(name, seed=3)
    est.start([0.0, 0.0], np.eye(2) * 1.0, 0, [], None, "init")
    before = (est.tracker.mean[0], est.tracker.mean[1])
    e, refused = _scan_at(est, 1.0, 40.0, 0.0)
    assert refused is not None and "40.0 m" in refused
    assert (e.x, e.y) == pytest.approx(before)
    e, refused = _scan_at(est, 2.0, 2.0, 0.0)  # a plausible fix is used again
    assert refused is None and e.x > before[0] + 0.3 and est.gated_in_a_row == 0


@pytest.mark.parametrize("name", ["ekf-xy", "ekf"])
def test_after_a_run_of_refused_fixes_the_covariance_grows_until_a_fix_passes(name):
    """The tracker, not the fixes, may be lost: after MAX_GATED_IN_A_ROW refusals each further
    fix the gate would refuse doubles the tracker's covariance first, so the far fixes are taken
    once the tracker's own uncertainty explains them (never blindly); the count is stored."""
    from server.estimation.session import GATE_D2, INFLATE_FACTOR, MAX_GATED_IN_A_ROW

    est = SessionEstimator(name, seed=3)
    est.start([0.0, 0.0], np.eye(2) * 1.0, 0, [], None, "init")
    for k in range(MAX_GATED_IN_A_ROW):
        est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        _, refused = _scan_at(est, float(k), 30.0, 30.0)
        assert refused is not None and est.gated_in_a_row == k + 1
    # Each further far fix doubles P before the gate looks again, until d² = 1800 / (P + s) passes
    # (s: the session's learned fix-noise scale: the far fixes teach a self-calibrating
    # tracker's to grow; a seed form's stays 1).
    from server.estimation.tracking.fixnoise import student_t_factor

    for k in range(30):
        P, s = est.tracker.covariance[0, 0], est.fix_noise.scale
        e, refused = _scan_at(est, 10.0 + k, 30.0, 30.0)
        inflated = INFLATE_FACTOR * P
        if refused is not None:
            assert est.gated_in_a_row == MAX_GATED_IN_A_ROW + k + 1
            assert est.tracker.covariance[0, 0] == pytest.approx(inflated)
            assert 1800.0 / (inflated + s) > GATE_D2
            continue
        d2 = 1800.0 / (inflated + s)
        assert d2 <= GATE_D2 and est.gated_in_a_row == 0
        # a self-calibrating tracker weighs the fix as a Student-t; a seed form as a Gaussian
        gain = inflated / (inflated + s * (student_t_factor(d2) if est.tracker.augmented else 1.0))
        assert (e.x, e.y) == pytest.approx((30.0 * gain, 30.0 * gain), abs=1e-6)
        break
    else:
        pytest.fail("the far fix never passed")


def test_time_order_is_stable_with_steps_first_at_equal_times():
    steps = [Step(2.0, 0.7, 0.0), Step(1.0, 0.7, 0.0)]
    scans = [Scan(1.0, {"wifi:a": -50.0})]
    assert [(k, i) for k, i, _ in time_order(steps, scans)] == [("step", 1), ("scan", 0), ("step", 0)]


def test_multilateration_fix_from_three_anchors():
    rss = {k: -45.0 - 25 * np.log10(np.hypot(b.x - 3.0, b.y - 4.0)) for k, b in BEACONS.items() if k.startswith("wifi")}
    fix = multilateration_fix(rss, BEACONS)
    assert fix.floor == 0 and np.hypot(fix.x - 3.0, fix.y - 4.0) < 0.5
    assert multilateration_fix({"wifi:unknown": -50.0}, BEACONS) is None


class _NoFixes:
    def fix(self, scan: Scan, near) -> Fix:
        raise NoFix("no model")


def test_walls_come_from_the_site_not_from_the_stored_state():
    """A session's state does not carry its floor's walls (a real plan has hundreds); each batch
    takes them from the site, so a plan imported while the session is open applies at once."""
    site = SiteMap(walls={(0, 0): [[-1.0, 5.0, 1.0, 5.0]]})
    est = SessionEstimator("pf-xy", seed=1)
    est.start([0.0, 0.0], None, 0, site.walls_of(0), None, "init")
    stored = json.loads(json.dumps(est.to_dict()))
    assert stored["tracker"]["walls"] == []
    back = SessionEstimator.from_dict(stored)
    back.apply_batch([Step(1.0, 0.7, 0.0)], [], _NoFixes(), site)
    assert back.tracker.walls.tolist() == [[-1.0, 5.0, 1.0, 5.0]]
    replanned = SiteMap(walls={(0, 0): [[-1.0, 5.0, 1.0, 5.0], [3.0, -1.0, 3.0, 1.0]]})
    back.apply_batch([Step(2.0, 0.7, 0.0)], [], _NoFixes(), replanned)
    assert len(back.tracker.walls) == 2


class _FixAt:
    """The fingerprint model's answer for every scan: here, on floor ``floor``, 0.5 m σ."""

    def __init__(self, x: float, y: float, floor: int):
        self.fix_ = Fix(x, y, floor, np.eye(2) * 0.25)

    def fix(self, scan: Scan, near) -> Fix:
        return self.fix_


def test_a_crowd_point_needs_the_strongest_positioned_transmitter_on_its_floor():
    """A tight estimate that agrees with its scan's fix is a crowd candidate, unless the strongest
    transmitter the scan hears that has a known floor is on another floor: a session and a map that
    agree on the wrong floor (a floor change not yet confirmed, a map that learned floor 1 where
    floor 0 is) must not teach the map more of it. Scans that hear no positioned transmitter keep the
    old rule."""
    site = SiteMap(beacons={"ble:down": Beacon("ble:down", 3.0, 4.0, 0), "ble:here": Beacon("ble:here", 5.0, 4.0, 1)})
    candidates = {}
    for name, rss in {"floor 1 strongest": {"ble:here": -60.0, "ble:down": -75.0},
                      "floor 0 strongest": {"ble:here": -78.0, "ble:down": -62.0},
                      "none positioned": {"wifi:x": -60.0, "wifi:y": -70.0, "wifi:z": -72.0}}.items():
        est = SessionEstimator("ekf", seed=1)
        est.start([4.0, 4.0], np.eye(2) * 0.25, 1, [], 0.0, "init")
        rss = {**rss, "wifi:a": -65.0, "wifi:b": -70.0}  # (the gate wants 3 transmitters)
        out = est.apply_batch([], [Scan(1.0, rss)], _FixAt(4.0, 4.0, 1), site, crowdsourcing=True)
        candidates[name] = len(out.crowd)
    assert candidates == {"floor 1 strongest": 1, "floor 0 strongest": 0, "none positioned": 1}
