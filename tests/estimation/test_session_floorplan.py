"""The walkable area reaches a session's PF through ``SiteMap.walkable`` (no walls given): a walk
whose PDR heading drifts into a closed room ends in the corridor, every estimate outside the room."""

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


def in_room(x, y):
    return 10 < x < 30 and y > 5


@pytest.mark.parametrize("name", ["pf", "pf-xy"])
def test_a_session_pf_never_ends_in_the_room_it_cannot_reach(name):
    plan = read_plan(PLAN, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))))
    assert plan.walkable is not None
    walk = [Step(0.5 * k, 0.7, 90.0 - 14.0, length_std_m=0.1, heading_std_deg=3.0) for k in range(40)]
    ends = {}
    for label, site in [("free", SiteMap()), ("plan", SiteMap(walkable={(0, 0): Walkable(plan.walkable)}))]:
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
