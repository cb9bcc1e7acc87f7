"""A floor's grid measured from its survey (``building_grid.survey_grids``): from the surveyors' walks
(device and time) or, without them, from the surveyed positions; the kernel mode where moves across
open space pull the mean; nothing where the moves go every way."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.estimation import building_grid
from server.estimation.building_grid import survey_grids
from server.estimation.tracking.selfcal import wrap_deg


def rotate(xy: np.ndarray, deg: float) -> np.ndarray:
    """Positions turned by ``deg`` clockwise (a segment along +y then heads ``deg``)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.column_stack((c * xy[:, 0] + s * xy[:, 1], -s * xy[:, 0] + c * xy[:, 1]))


def loop(every_m: float, width: float = 40.0, height: float = 20.0) -> np.ndarray:
    """Points every ``every_m`` along a rectangular corridor loop."""
    u = np.arange(0.0, 2 * (width + height), every_m)
    out = []
    for v in u:
        if v < width:
            out.append((v, 0.0))
        elif v < width + height:
            out.append((width, v - width))
        elif v < 2 * width + height:
            out.append((2 * width + height - v, height))
        else:
            out.append((0.0, 2 * (width + height) - v))
    return np.array(out)


def grids_of(xy, device=None, t=None, floor=None, building=None):
    n = len(xy)
    return survey_grids(np.zeros(n, int) if building is None else building, np.zeros(n, int) if floor is None else floor,
                        xy[:, 0], xy[:, 1], device, t)


@pytest.mark.parametrize("deg", [0.0, 10.8, 33.0, -27.5])
def test_a_walk_around_a_rotated_loop_gives_its_grid(deg):
    xy = rotate(loop(0.7), deg)
    (g,) = grids_of(xy, device=np.array(["phone"] * len(xy), object), t=np.arange(len(xy), dtype=float))
    assert g.source == "walks" and g.resultant > 0.95 and g.segments == len(xy) - 1
    assert wrap_deg(g.deg - deg, 90.0) == pytest.approx(0.0, abs=building_grid.MODE_STEP_DEG)


@pytest.mark.parametrize("deg", [0.0, 21.0, -40.0])
def test_a_static_survey_every_2_m_gives_its_axes(deg):
    xy = np.repeat(rotate(loop(2.0), deg), 3, axis=0)  # three scans a point, no device or time
    (g,) = grids_of(xy)
    assert g.source == "points" and g.resultant > 0.9
    assert wrap_deg(g.deg - deg, 90.0) == pytest.approx(0.0, abs=building_grid.MODE_STEP_DEG)


def test_the_mode_keeps_the_corridors_where_moves_across_open_space_pull_the_mean():
    # 70 % of the walked length along corridors at 10°, 30 % across an atrium at 35°
    rng = np.random.default_rng(0)
    headings = np.where(rng.random(400) < 0.7, 10.0, 35.0) + 90.0 * rng.integers(0, 4, 400)
    moves = 1.4 * np.column_stack((np.sin(np.radians(headings)), np.cos(np.radians(headings))))
    xy = np.vstack(([0.0, 0.0], np.cumsum(moves, axis=0)))
    (g,) = grids_of(xy, device=np.array(["a"] * len(xy), object), t=np.arange(len(xy), dtype=float))
    strength, mean = building_grid._resultant(moves[:, 0], moves[:, 1], np.hypot(moves[:, 0], moves[:, 1]))
    assert abs(mean - 10.0) > 3.0  # the circular mean is pulled towards the atrium
    assert g.deg == pytest.approx(10.0, abs=0.5)
    assert strength == pytest.approx(g.resultant, abs=1e-3)


def test_moves_every_way_show_no_grid():
    rng = np.random.default_rng(1)
    h = rng.uniform(0.0, 2 * math.pi, 500)
    xy = np.vstack(([0.0, 0.0], np.cumsum(np.column_stack((np.sin(h), np.cos(h))), axis=0)))
    assert grids_of(xy, device=np.array(["a"] * len(xy), object), t=np.arange(len(xy), dtype=float)) == []
    assert grids_of(rng.uniform(0.0, 50.0, (300, 2))) == []  # scattered positions


def test_each_floor_of_each_building_gets_its_own_grid():
    a, b = rotate(loop(0.7), 5.0), rotate(loop(0.7), -20.0)
    xy = np.vstack((a, b))
    floor = np.r_[np.zeros(len(a), int), np.ones(len(b), int)]
    building = np.r_[np.zeros(len(a), int), np.full(len(b), 2)]
    device = np.array(["p"] * len(xy), object)
    found = grids_of(xy, device=device, t=np.arange(len(xy), dtype=float), floor=floor, building=building)
    assert [(g.building, g.floor) for g in found] == [(0, 0), (2, 1)]
    assert found[0].deg == pytest.approx(5.0, abs=0.25) and found[1].deg == pytest.approx(-20.0, abs=0.25)


def test_a_survey_of_few_moves_is_read_by_its_positions_and_unknown_devices_are_not_walks():
    xy = rotate(loop(2.0), 15.0)
    device = np.array([None] * len(xy), object)
    device[:5] = "short"  # four moves of one device: too few to be walks
    t = np.full(len(xy), np.nan)
    t[:5] = np.arange(5.0)
    (g,) = grids_of(xy, device=device, t=t)
    assert g.source == "points" and g.deg == pytest.approx(15.0, abs=0.25)
    moves = building_grid.walk_segments(xy[:, 0], xy[:, 1], device, t)
    assert len(moves) == 4


def test_moves_too_short_or_too_long_are_not_walking():
    xy = np.array([[0.0, 0.0], [0.0, 0.1], [0.0, 1.0], [0.0, 30.0], [0.0, 31.0]])
    moves = building_grid.walk_segments(xy[:, 0], xy[:, 1], np.array(["d"] * 5, object), np.arange(5.0))
    np.testing.assert_allclose(moves, [[0.0, 0.9], [0.0, 1.0]])  # standing still and a 29 m gap left out


def test_surveyors_hopping_between_points_in_any_order_show_the_grid_by_where_they_stand():
    # Four surveyors visit the points of a 1.5 m lattice (turned 20°) in random order: their moves
    # go every way, the points they stood on lie on the grid.
    rng = np.random.default_rng(3)
    points = rotate(np.array([(1.5 * i, 1.5 * j) for i in range(6) for j in range(5)]), 20.0)
    visits = np.vstack([points[rng.permutation(len(points))] for _ in range(4)])
    device = np.repeat(np.array(["s0", "s1", "s2", "s3"], object), len(points))
    t = np.arange(len(visits), dtype=float)
    moves = building_grid.walk_segments(visits[:, 0], visits[:, 1], device, t)
    assert len(moves) >= building_grid.MIN_WALK_SEGMENTS
    assert building_grid._grid_of(moves) is None  # the moves agree on no grid
    (g,) = grids_of(visits, device=device, t=t)
    assert g.source == "points" and g.deg == pytest.approx(20.0, abs=0.25)
