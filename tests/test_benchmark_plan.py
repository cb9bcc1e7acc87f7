"""The held-out simulator's floor plan (``benchmarks/scenario_family.py --plan``) fits its walks:
every true position is walkable and no true step crosses a wall, while the loop's middle is not
walkable — so the figures measured with it judge the trackers, not an impossible plan."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.scenario_family import World, draw, walk
from server.estimation.tracking.geometry import crosses_walls


@pytest.mark.parametrize(("split", "index"), [("heldout", 0), ("heldout", 5), ("tune", 3)])
def test_the_loop_plan_holds_the_true_walk(split, index):
    world = World(draw(split, index))
    walls, walkable = world.plan(3.0)
    truth = walk(world).truth
    assert walkable.contains(truth).all()
    assert not crosses_walls(truth[:-1], truth[1:], np.asarray(walls, float)).any()
    W, H = world.sc.width_m, world.sc.height_m
    assert not walkable.contains(np.array([[W / 2, H / 2], [-3.0, -3.0]])).any()
