"""Floor plans: a lon/lat GeoJSON plan through its bbox transform gives walls and walkable space
where the site frame says; the wall index agrees with the all-pairs test; bad plans are refused."""

import numpy as np
import pytest
import shapely

from server.estimation.floorplan import PlanError, Transform, Walkable, WallIndex, read_plan
from server.estimation.tracking.geometry import crosses_walls
from tests.helpers.floorplans import HEIGHT_M, WIDTH_M, plan_geojson

W, H = WIDTH_M, HEIGHT_M


def segments(walls):
    """Walls as a set of undirected segments rounded to cm."""
    return {tuple(sorted([tuple(np.round(w[:2], 2)), tuple(np.round(w[2:], 2))])) for w in np.asarray(walls)}


def test_bbox_transform_puts_walls_and_walkable_space_at_the_site_coordinates():
    plan = read_plan(plan_geojson(), bbox_size=(W, H))
    area = Walkable(plan.walkable)
    assert area.geometry.area == pytest.approx(200 * 100 - 100 * 60, rel=1e-6)
    inside = area.contains(np.array([[10, 10], [100, 20], [190, 90], [100, 70], [250, 50], [-1, 50]]))
    assert inside.tolist() == [True, True, True, False, False, False]
    # the walls are where walkable space ends: the outline, and the store's sides inside the floor
    walls = segments(plan.walls)
    for seg in [((0, 0), (200, 0)), ((50, 40), (150, 40)), ((50, 40), (50, 100)), ((150, 40), (150, 100))]:
        assert tuple(sorted(seg)) in walls or any(
            crosses_walls(np.array([[(seg[0][0] + seg[1][0]) / 2 - 0.01, (seg[0][1] + seg[1][1]) / 2 - 0.01]]),
                          np.array([[(seg[0][0] + seg[1][0]) / 2 + 0.01, (seg[0][1] + seg[1][1]) / 2 + 0.01]]),
                          plan.walls))
    # a walk from the corridor into the store crosses a wall; along the corridor it does not
    assert crosses_walls(np.array([[100.0, 20.0]]), np.array([[100.0, 60.0]]), plan.walls).tolist() == [True]
    assert crosses_walls(np.array([[10.0, 20.0]]), np.array([[190.0, 20.0]]), plan.walls).tolist() == [False]


def test_an_explicit_matrix_transform():
    # metres given directly, then moved by (+10, −5) and turned a quarter (x' = −y + 10, y' = x − 5)
    fc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"category": "floor"},
         "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [4, 0], [4, 2], [0, 2], [0, 0]]]}}]}
    plan = read_plan(fc, Transform(((0.0, -1.0, 10.0), (1.0, 0.0, -5.0))))
    area = Walkable(plan.walkable)
    assert area.contains(np.array([[9.0, -3.0], [9.0, -6.0], [11.0, -3.0]])).tolist() == [True, False, False]
    assert len(plan.walls) == 4


def test_walls_only_plans_and_line_features():
    fc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "LineString", "coordinates": [[0, 0], [10, 0], [10, 5]]}},
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon",
                                                           "coordinates": [[[20, 0], [22, 0], [22, 2], [20, 0]]]}}]}
    plan = read_plan(fc, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))))
    assert plan.walkable is None
    assert len(plan.walls) == 2 + 3


def test_a_walkable_area_with_holes_is_stored_as_hole_free_rings():
    """A floor with a store in its middle: the corridor around it is a polygon with a hole, stored
    as exterior rings only whose union is the same area."""
    fc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"type": "floor"},
         "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]]]}},
        {"type": "Feature", "properties": {},
         "geometry": {"type": "Polygon", "coordinates": [[[2, 2], [8, 2], [8, 8], [2, 8], [2, 2]]]}}]}
    plan = read_plan(fc, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))))
    assert plan.walkable is not None and len(plan.walkable) >= 2
    rings = [shapely.Polygon(r) for r in plan.walkable]
    assert all(not p.interiors for p in rings)
    area = Walkable(plan.walkable)
    assert area.geometry.area == pytest.approx(100 - 36)
    assert area.contains(np.array([[1, 1], [5, 5], [9, 5], [5, 9.5]])).tolist() == [True, False, True, True]
    # the walls are the real boundary (outline and store), not the cuts
    assert len(plan.walls) == 8


def test_the_wall_index_agrees_with_the_all_pairs_test():
    rng = np.random.default_rng(5)
    walls = np.column_stack([rng.uniform(0, 50, (300, 2)), rng.uniform(0, 50, (300, 2))])
    walls[:100, 3] = walls[:100, 1]  # axis-parallel walls have flat boxes
    walls[100:150, 2] = walls[100:150, 0]
    start = rng.uniform(0, 50, (2000, 2))
    end = start + rng.normal(0, 1.0, (2000, 2))
    end[:200, 0] = start[:200, 0]  # moves straight north/south
    expected = crosses_walls(start, end, walls)
    assert 0.05 < expected.mean() < 0.95
    np.testing.assert_array_equal(WallIndex(walls).crosses(start, end), expected)


@pytest.mark.parametrize("geojson, transform, message", [
    ([1, 2], None, "GeoJSON object"),
    ({"type": "Polygon", "coordinates": []}, None, "FeatureCollection or Feature"),
    ({"type": "FeatureCollection"}, None, "'features' list"),
    ({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
      "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [1, "a"], [1, 1], [0, 0]]]}}]}, None, "[x, y] numbers"),
    ({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
      "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [1, float("nan")], [1, 1], [0, 0]]]}}]}, None,
     "non-finite"),
    ({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
      "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [0, 0]]]}}]}, None, "invalid Polygon"),
    ({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
      "geometry": {"type": "Point", "coordinates": [0, 0]}}]}, None, "no Polygon"),
    (None, Transform(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))), "GeoJSON object"),
])
def test_bad_plans_are_refused_naming_the_problem(geojson, transform, message):
    with pytest.raises(PlanError, match=message.replace("[", r"\[").replace("]", r"\]")):
        read_plan(geojson, transform, bbox_size=(10.0, 10.0))


def test_bad_transforms_and_too_big_plans_are_refused(monkeypatch):
    with pytest.raises(PlanError, match="degenerate"):
        Transform(((1.0, 2.0, 0.0), (2.0, 4.0, 0.0)))
    with pytest.raises(PlanError, match="non-finite"):
        Transform(((1.0, 0.0, float("inf")), (0.0, 1.0, 0.0)))
    with pytest.raises(PlanError, match="2×3"):
        Transform(((1.0, 0.0), (0.0, 1.0)))  # type: ignore[arg-type]
    line = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
            "geometry": {"type": "LineString", "coordinates": [[0, 0], [5, 0]]}}]}
    with pytest.raises(PlanError, match="bounding box is degenerate"):
        read_plan(line, bbox_size=(10.0, 10.0))
    monkeypatch.setattr("server.estimation.floorplan.MAX_VERTICES", 5)
    with pytest.raises(PlanError, match="10 vertices, more than 5"):
        read_plan(plan_geojson(), bbox_size=(W, H))


def test_nearest_inside_moves_only_the_points_outside_to_the_nearest_point_of_the_area():
    from server.estimation.floorplan import Walkable

    area = Walkable([[[0.0, 0.0], [10.0, 0.0], [10.0, 2.0], [0.0, 2.0]]])  # a 10 × 2 m corridor
    points = np.array([[5.0, 1.0], [5.0, 3.5], [-1.0, -1.0], [12.0, 1.5], [10.0, 2.0]])
    moved = area.nearest_inside(points)
    np.testing.assert_allclose(moved, [[5.0, 1.0], [5.0, 2.0], [0.0, 0.0], [10.0, 1.5], [10.0, 2.0]], atol=1e-9)
    assert points[1, 1] == 3.5  # a new array
