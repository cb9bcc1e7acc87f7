"""Where the floor has a walkable area, every estimate a session reports lies in it (the walkable
point nearest the tracker's mean), for every filter, while the tracker and the stored whole state
keep their own mean; a floor change and a cold start use the right floor's area."""

from __future__ import annotations

import numpy as np
import pytest

from server.estimation.floorplan import Walkable
from server.estimation.session import SessionEstimator
from server.estimation.tracking import tracker_names
from server.estimation.types import Fix, Scan, SiteMap, Step

#: floor 0: a corridor 60 m long (x) and 3 m wide; floor 1: a hall x, y ∈ [20, 40]
CORRIDOR = Walkable([[[0.0, 0.0], [60.0, 0.0], [60.0, 3.0], [0.0, 3.0]]])
HALL = Walkable([[[20.0, 20.0], [40.0, 20.0], [40.0, 40.0], [20.0, 40.0]]])
PLAN = SiteMap(walkable={(0, 0): CORRIDOR, (0, 1): HALL})
#: east along the corridor, the compass reading 12° too far north: the dead reckoning leaves it
WALK = [Step(0.5 * (k + 1), 0.7, 78.0, length_std_m=0.05, heading_std_deg=3.0) for k in range(60)]


class FixesAt:
    """Every scan's fix is the given point on the given floor."""

    def __init__(self, xy, floor: int, std_m: float = 2.0):
        self.fix_ = Fix(float(xy[0]), float(xy[1]), floor, np.eye(2) * std_m**2)

    def fix(self, scan, near):
        return self.fix_


class NoFixes:
    def fix(self, scan, near):  # pragma: no cover - the walks below have no scans
        raise AssertionError("no scan in this walk")


def _walk(name: str, site: SiteMap):
    est = SessionEstimator(name, seed=5)
    est.start([1.0, 1.5], np.eye(2) * 0.25, 0, [], None, "init")
    out = []
    for k in range(0, len(WALK), 10):  # batches, the state stored and loaded between them
        est = SessionEstimator.from_dict(est.to_dict())
        o = est.apply_batch(WALK[k:k + 10], [], NoFixes(), site)
        out += list(zip(o.estimates, o.states, strict=True))
    return est, out


@pytest.mark.parametrize("name", tracker_names())
def test_every_estimate_is_in_the_walkable_area_and_the_tracker_keeps_its_own_mean(name):
    free_est, free = _walk(name, SiteMap())
    plan_est, plan = _walk(name, PLAN)
    assert all(bool(CORRIDOR.contains(np.array([[e.x, e.y]]))[0]) for e, _ in plan)
    if name.startswith("pf"):  # the PF's own walls: its cloud stays in the corridor anyway
        return
    # the Gaussian trackers know nothing of the plan: their dead reckoning left the corridor...
    assert free[-1][0].y > 8.0
    # ...and with the plan they compute exactly the same, only the reported position moves
    assert np.allclose(plan_est.tracker.mean, free_est.tracker.mean)
    for (e_free, s_free), (e_plan, s_plan) in zip(free, plan, strict=True):
        assert s_plan == s_free  # the stored whole state (None for the seed forms) is the tracker's
        expected = CORRIDOR.nearest_inside(np.array([[e_free.x, e_free.y]]))[0]
        assert (e_plan.x, e_plan.y) == pytest.approx(tuple(expected), abs=1e-9)
        assert e_plan.covariance == e_free.covariance
    # and the reported end is nearer the true one (x = 1 + 60 · 0.7, in the corridor)
    truth = np.array([43.0, 1.5])
    assert np.hypot(plan[-1][0].x - truth[0], plan[-1][0].y - truth[1]) < \
        np.hypot(free[-1][0].x - truth[0], free[-1][0].y - truth[1])


@pytest.mark.parametrize("name", ["skpf", "ekf", "kf"])
def test_a_cold_start_and_a_floor_change_report_inside_that_floors_area(name):
    est = SessionEstimator(name, seed=5)
    # a cold start on a fix outside the corridor (y = 6)
    est.apply_batch([], [Scan(1.0, {"wifi:a": -60.0})], FixesAt((30.0, 6.0), 0), PLAN)
    assert est.estimate is not None
    assert (est.estimate.x, est.estimate.y) == pytest.approx((30.0, 3.0))
    # three agreeing fixes on floor 1 outside its hall confirm the floor change
    out = est.apply_batch([], [Scan(2.0 + k, {"wifi:a": -60.0}) for k in range(3)], FixesAt((45.0, 30.0), 1), PLAN)
    last = out.estimates[-1]
    assert last.floor == 1
    assert (last.x, last.y) == pytest.approx((40.0, 30.0))
