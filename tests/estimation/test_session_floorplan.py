"""A floor plan reaches a session's tracker through ``SiteMap``: a walk whose PDR heading drifts
into a closed room ends in the corridor, every estimate outside the room. The PF kills particles
outside the walkable area (given alone); the self-calibrating Gaussian filters truncate their
Gaussian at the plan's walls (given with it, as the server gives both)."""

import numpy as np
import pytest

from server.estimation.floorplan import Transform, Walkable, read_plan
from server.estimation.session import SessionEstimator
from server.estimation.types import SiteMap, Step

# 40 × 10 m floor; its north half between x = 10 and 30 is a room without a door
PLAN = {"type": "FeatureCollection", "features": [
    {"type": "Feature", "properties": {"type": "floor"},
     "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [40, 0], [40, 10], [0, 10], [0, 0]]]}},
    {"type": "Feature", "properties": {},
     "geometry": {"type": "Polygon", "coordinates": [[[10, 5], [30, 5], [30, 10], [10, 10], [10, 5]]]}}]}


class NoFixes:
    def fix(self, scan, near):  # pragma: no cover - the walk has no scans
        raise AssertionError("no scan in this walk")


def plan_site(plan, name: str) -> SiteMap:
    walls = {} if name.startswith("pf") else {(0, 0): plan.walls.tolist()}
    return SiteMap(walls=walls, walkable={(0, 0): Walkable(plan.walkable)})


def in_room(x, y):
    return 10 < x < 30 and y > 5


@pytest.mark.parametrize("name", ["pf", "pf-xy", "ekf", "ukf", "skpf"])
def test_a_session_pf_never_ends_in_the_room_it_cannot_reach(name):
    plan = read_plan(PLAN, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))))
    assert plan.walkable is not None
    walk = [Step(0.5 * k, 0.7, 90.0 - 14.0, length_std_m=0.1, heading_std_deg=3.0) for k in range(40)]
    ends = {}
    for label, site in [("free", SiteMap()), ("plan", plan_site(plan, name))]:
        est = SessionEstimator(name, seed=11)
        est.start([2.0, 2.0], np.eye(2) * 0.05, 0, [], None, "init")
        track = []
        for k in range(0, 40, 5):  # batches of 5 steps, the state stored and loaded between them
            est = SessionEstimator.from_dict(est.to_dict())
            track += est.apply_batch(walk[k:k + 5], [], NoFixes(), site).estimates
        ends[label] = track[-1]
        if label == "plan":
            assert not any(in_room(e.x, e.y) for e in track)
    assert in_room(ends["free"].x, ends["free"].y)  # without the plan the walk does end in the room
    assert ends["plan"].x > 20.0


@pytest.mark.parametrize("name", ["ekf", "ukf", "skpf"])
def test_being_pushed_back_from_the_room_teaches_the_heading_bias(name):
    """The walker heads 14° left of east along the room's wall: each truncation moves the state's
    heading bias towards east with the position (through their correlation)."""
    plan = read_plan(PLAN, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))))
    assert plan.walkable is not None
    site = plan_site(plan, name)
    est = SessionEstimator(name, seed=3)
    est.start([10.5, 2.0], np.eye(2) * 0.05, 0, [], None, "init")
    walk = [Step(0.5 * k, 0.7, 90.0 - 14.0, length_std_m=0.1, heading_std_deg=3.0) for k in range(40)]
    est.apply_batch(walk, [], NoFixes(), site)
    assert est.tracker is not None
    assert est.tracker.heading_bias_deg > 2.0  # learned from the walls alone: no fix in this walk


@pytest.mark.parametrize("name", ["pf", "pf-xy", "ekf-xy", "kf"])
def test_particle_and_seed_filters_leave_their_mean_where_it_is(name):
    """The PF keeps to the plan particle by particle (its mean may fall between them, in an
    obstacle); the seed forms do not use the plan. Neither moves a mean that crossed a wall."""
    from server.estimation.tracking import make_tracker

    plan = read_plan(PLAN, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))))
    assert plan.walkable is not None
    tracker = make_tracker(name, [20.0, 8.0], np.eye(2) * 0.05, seed=1)
    tracker.set_walkable(Walkable(plan.walkable))
    tracker.set_walls(plan.walls)
    before = tracker.mean
    assert tracker.keep_walkable(np.array([20.0, 3.0])) is False
    assert np.allclose(tracker.mean, before)
