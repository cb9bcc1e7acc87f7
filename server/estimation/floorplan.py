"""Floor plans: a GeoJSON plan turned into the site frame's walls and walkable area.

A plan is a GeoJSON FeatureCollection in any planar frame (the MSFT competition's are in
longitude/latitude). An affine ``Transform`` takes it into the site frame (metres, x east,
y north): an explicit 2×3 matrix, or ``Transform.bbox``, which maps the plan's bounding box
onto [0, width] × [0, height] (the MSFT convention; checked on the shared walks in
``docs/msft-evaluation.md``: every waypoint falls inside the floor outline and none in a
store).

Which features are what:

* a Polygon/MultiPolygon whose ``properties.type`` or ``properties.category`` is ``"floor"``
  is walkable (the floor's outline);
* every other Polygon/MultiPolygon is an obstacle the walker does not enter (a store, a
  pillar, a room without a door in the plan);
* LineString/MultiLineString features are walls; points and other geometries are ignored.

The walkable area is the union of the outlines minus the obstacles (None when the plan has
no outline), and the walls are its boundary (where walkable space ends) plus the line
features; without an outline, every polygon's boundary is a wall.

Stored form of a walkable area (``Floor.walkable``): a list of polygons, each its exterior ring
``[[x, y], ...]``; the area is their union. A walkable area with holes (a corridor around a
store) is cut into hole-free pieces by vertical lines through the holes. ``Walkable`` answers point-in-area for many points
at once and ``WallIndex`` which moves cross a wall, both through a grid of cells so that a
PF step over 1,000 particles tests only what is near them (``benchmarks/floorplan_cost.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from shapely.geometry.base import BaseGeometry

from server.estimation.tracking.geometry import crosses_walls, segments_cross

#: the most vertices a plan may have (the MSFT site-1 F1 plan has 1,182; a floor stores at most
#: 100,000 walkable points)
MAX_VERTICES = 100_000
#: a transform whose 2×2 part has |det| below this is degenerate (collapses the plan)
MIN_DET = 1e-12
#: below this many walls the all-pairs crossing test is cheaper than the index
INDEX_FROM_WALLS = 64

Ring = list[list[float]]


class PlanError(ValueError):
    """The plan or its transform is unusable; the message names the problem and ``part`` says
    which ("geojson" or "transform")."""

    def __init__(self, msg: str, part: str = "geojson"):
        super().__init__(msg)
        self.part = part


@dataclass(frozen=True)
class Transform:
    """x' = a·x + b·y + c, y' = d·x + e·y + f, ``matrix`` = ((a, b, c), (d, e, f))."""

    matrix: tuple[tuple[float, float, float], tuple[float, float, float]]

    def __post_init__(self) -> None:
        m = np.asarray(self.matrix, float)
        if m.shape != (2, 3):
            raise PlanError("transform matrix must be 2×3 [[a, b, c], [d, e, f]]", "transform")
        if not np.all(np.isfinite(m)):
            raise PlanError("transform matrix has a non-finite entry", "transform")
        with np.errstate(over="ignore", invalid="ignore"):
            det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
        if not math.isfinite(det):
            raise PlanError("transform scale is out of range (its determinant is not finite)", "transform")
        if abs(det) < MIN_DET:
            raise PlanError("transform is degenerate (its 2×2 part has determinant 0)", "transform")

    @classmethod
    def bbox(cls, bounds: Sequence[float], width_m: float, height_m: float) -> Transform:
        """Map the box (xmin, ymin, xmax, ymax) onto [0, width_m] × [0, height_m], axes kept."""
        x0, y0, x1, y1 = (float(v) for v in bounds)
        if not (math.isfinite(width_m) and math.isfinite(height_m) and width_m > 0 and height_m > 0):
            raise PlanError("bbox transform needs a positive width and height", "transform")
        if not (x1 > x0 and y1 > y0):
            raise PlanError("the plan's bounding box is degenerate (zero width or height)")
        sx, sy = width_m / (x1 - x0), height_m / (y1 - y0)
        return cls(((sx, 0.0, -x0 * sx), (0.0, sy, -y0 * sy)))

    def apply(self, geom: BaseGeometry) -> BaseGeometry:
        (a, b, c), (d, e, f) = self.matrix
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is refused by the caller
            return shapely.transform(geom, lambda xy: xy @ np.array([[a, d], [b, e]]) + np.array([c, f]))


@dataclass(frozen=True)
class FloorPlan:
    """A plan in the site frame: wall segments (n, 4), the walkable rings (None: no outline) and
    the transform that took it there."""

    walls: np.ndarray
    walkable: list[Ring] | None
    transform: Transform


# --------------------------------------------------------------------------- reading
def _features(geojson: Any) -> list[dict]:
    if not isinstance(geojson, dict):
        raise PlanError("geojson must be a GeoJSON object")
    kind = geojson.get("type")
    if kind == "FeatureCollection":
        feats = geojson.get("features")
        if not isinstance(feats, list):
            raise PlanError("geojson FeatureCollection has no 'features' list")
        return feats
    if kind == "Feature":
        return [geojson]
    raise PlanError(f"geojson type must be FeatureCollection or Feature, not {kind!r}")


def _is_outline(props: Any) -> bool:
    if not isinstance(props, dict):
        return False
    return any(isinstance(props.get(k), str) and props[k].lower() == "floor" for k in ("type", "category"))


def _coords(value: Any, depth: int, where: str) -> np.ndarray | list:
    """Check nested coordinate lists of the given depth (1: a position list) and count them."""
    if depth == 0:
        if not (isinstance(value, list) and len(value) >= 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value[:2])):
            raise PlanError(f"{where}: a position must be [x, y] numbers")
        if not (math.isfinite(value[0]) and math.isfinite(value[1])):
            raise PlanError(f"{where}: non-finite coordinate {value[:2]}")
        return value[:2]
    if not isinstance(value, list):
        raise PlanError(f"{where}: coordinates must be nested lists")
    return [_coords(v, depth - 1, where) for v in value]


_DEPTH = {"Polygon": 2, "MultiPolygon": 3, "LineString": 1, "MultiLineString": 2}


def _count(coords: Any) -> int:
    return 1 if coords and not isinstance(coords[0], list) else sum(_count(c) for c in coords)


def _geometry(feature: Any, i: int) -> tuple[str, BaseGeometry] | None:
    """(role, geometry) of one feature: role "outline", "obstacle" or "wall"; None: ignored."""
    where = f"features[{i}]"
    if not isinstance(feature, dict) or feature.get("type") != "Feature":
        raise PlanError(f"{where} is not a GeoJSON Feature")
    geom = feature.get("geometry")
    if geom is None:
        return None
    if not isinstance(geom, dict) or not isinstance(geom.get("type"), str):
        raise PlanError(f"{where}: geometry must be a GeoJSON geometry object")
    kind = geom["type"]
    if kind not in _DEPTH:
        return None  # points (labels) and the like say nothing about walls
    coords = _coords(geom.get("coordinates"), _DEPTH[kind], where)
    parts = {"LineString": [coords], "MultiLineString": coords, "Polygon": coords}.get(kind) or \
        [ring for poly in coords for ring in poly]
    least = 4 if kind in ("Polygon", "MultiPolygon") else 2
    if any(len(r) < least for r in parts):
        raise PlanError(f"{where}: invalid {kind}: a {'line' if least == 2 else 'ring'} needs at least {least} positions")
    try:
        shape = shapely.geometry.shape({"type": kind, "coordinates": coords})
    except (ValueError, TypeError, shapely.errors.GEOSException) as exc:
        raise PlanError(f"{where}: invalid {kind}: {exc}") from None
    if kind in ("LineString", "MultiLineString"):
        return "wall", shape
    if not shape.is_valid:
        shape = shapely.make_valid(shape)  # self-touching rings and the like: repaired, not refused
    return ("outline" if _is_outline(feature.get("properties")) else "obstacle"), shape


def count_vertices(geojson: Any) -> int:
    """How many positions the plan's line and polygon features hold (before any other check)."""
    n = 0
    for f in _features(geojson):
        geom = f.get("geometry") if isinstance(f, dict) else None
        if isinstance(geom, dict) and geom.get("type") in _DEPTH and isinstance(geom.get("coordinates"), list):
            n += _count(geom["coordinates"])
    return n


def _bounds(geoms: list[BaseGeometry]) -> tuple[float, float, float, float]:
    if not geoms:
        raise PlanError("the plan has no Polygon, MultiPolygon, LineString or MultiLineString feature")
    x0, y0, x1, y1 = shapely.total_bounds(np.array(geoms, dtype=object))
    return float(x0), float(y0), float(x1), float(y1)


def _read(geojson: Any) -> list[tuple[str, BaseGeometry]]:
    n = count_vertices(geojson)
    if n > MAX_VERTICES:
        raise PlanError(f"the plan has {n} vertices, more than {MAX_VERTICES}")
    out = [g for i, f in enumerate(_features(geojson)) if (g := _geometry(f, i)) is not None]
    if not out:
        raise PlanError("the plan has no Polygon, MultiPolygon, LineString or MultiLineString feature")
    return out


def read_plan(geojson: Any, transform: Transform | None = None, *, bbox_size: tuple[float, float] | None = None
              ) -> FloorPlan:
    """The plan's walls and walkable area in the site frame, through ``transform`` or, with
    ``bbox_size`` = (width, height), through ``Transform.bbox`` of the plan's bounds.
    Raises ``PlanError`` naming what is wrong."""
    parts = _read(geojson)
    if transform is None:
        if bbox_size is None:
            raise PlanError("give a transform matrix or a bbox size", "transform")
        transform = Transform.bbox(_bounds([g for _, g in parts]), *bbox_size)
    parts = [(role, transform.apply(g)) for role, g in parts]
    if not all(np.all(np.isfinite(shapely.get_coordinates(g))) for _, g in parts):
        raise PlanError("the transform takes the plan to non-finite coordinates", "transform")
    outlines = [g for role, g in parts if role == "outline"]
    obstacles = [g for role, g in parts if role == "obstacle"]
    lines = [g for role, g in parts if role == "wall"]
    walkable: BaseGeometry | None = None
    if outlines:
        walkable = shapely.union_all(outlines)
        if obstacles:
            walkable = walkable.difference(shapely.union_all(obstacles))
        walkable = _polygonal(walkable)
        if walkable.is_empty:
            raise PlanError("the walkable area is empty (the obstacles cover the floor outline)")
        bounds = [walkable.boundary]
    else:
        bounds = [g.boundary for g in obstacles]
    walls = np.concatenate([_segments(g) for g in bounds + lines]) if bounds + lines else np.zeros((0, 4))
    if walkable is None and len(walls) == 0:
        raise PlanError("the plan gives neither a wall nor a walkable area (its shapes have no area or length)")
    return FloorPlan(walls=walls, walkable=None if walkable is None else _rings(walkable), transform=transform)


def _polygonal(geom: BaseGeometry) -> BaseGeometry:
    """Only the polygons of a geometry (a difference may leave stray lines or points)."""
    polys = [g for g in shapely.get_parts(geom) if g.geom_type in ("Polygon", "MultiPolygon") and not g.is_empty]
    return shapely.union_all(polys) if polys else shapely.Polygon()


def _segments(geom: BaseGeometry) -> np.ndarray:
    """Every consecutive pair of vertices of every line of ``geom`` as [x1, y1, x2, y2]."""
    out = []
    for line in shapely.get_parts(geom):
        xy = shapely.get_coordinates(line)
        if len(xy) >= 2:
            seg = np.hstack([xy[:-1], xy[1:]])
            out.append(seg[np.any(seg[:, :2] != seg[:, 2:], axis=1)])
    return np.concatenate(out) if out else np.zeros((0, 4))


def _rings(geom: BaseGeometry) -> list[Ring]:
    """The area as exterior rings only (their union is the area): a polygon with holes is cut
    into hole-free pieces by vertical lines through each hole (rounded to 0.1 mm)."""
    rings = []
    for poly in _hole_free(geom):
        rings.append([[round(float(x), 4), round(float(y), 4)] for x, y in poly.exterior.coords])
    return rings


def _hole_free(geom: BaseGeometry, depth: int = 0) -> list[shapely.Polygon]:
    out: list[shapely.Polygon] = []
    for poly in shapely.get_parts(geom):
        if not poly.interiors or depth > 2:
            out.append(poly)
            continue
        x0, y0, x1, y1 = poly.bounds
        cuts = sorted({float(shapely.Polygon(h).representative_point().x) for h in poly.interiors})
        edges = [x0, *cuts, x1]
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            if b > a:
                out += _hole_free(_polygonal(poly.intersection(shapely.box(a, y0 - 1, b, y1 + 1))), depth + 1)
    return [p for p in out if p.area > 0]


# --------------------------------------------------------------------------- using
def union_of(rings: Sequence[Sequence[Sequence[float]]]) -> BaseGeometry:
    """The area inside any of ``rings`` (each the exterior of a polygon)."""
    polys = [shapely.Polygon(r) for r in rings if len(r) >= 3]
    polys = [p if p.is_valid else _polygonal(shapely.make_valid(p)) for p in polys]
    polys = [p for p in polys if not p.is_empty and p.area > 0]
    if not polys:
        raise PlanError("a walkable area needs at least one ring of 3 or more points around some area")
    return _polygonal(shapely.union_all(polys))


class _Grid:
    """Square cells of ``cell_m`` over a box: a point's cell index, −1 outside the box."""

    def __init__(self, bounds: Sequence[float], cell_m: float):
        x0, y0, x1, y1 = (float(v) for v in bounds)
        self.origin = np.array([x0, y0])
        self.cell = float(cell_m)
        self.nx = max(int(math.ceil((x1 - x0) / self.cell)), 1)
        self.ny = max(int(math.ceil((y1 - y0) / self.cell)), 1)

    def ij(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Column and row of each point (not clipped)."""
        k = np.floor((xy - self.origin) / self.cell).astype(np.int64)
        return k[:, 0], k[:, 1]

    def cell_of(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        ok = (i >= 0) & (i < self.nx) & (j >= 0) & (j < self.ny)
        return np.where(ok, j * self.nx + i, -1)

    def boxes(self) -> np.ndarray:
        i, j = np.meshgrid(np.arange(self.nx), np.arange(self.ny))
        x0 = self.origin[0] + i.ravel() * self.cell
        y0 = self.origin[1] + j.ravel() * self.cell
        return shapely.box(x0, y0, x0 + self.cell, y0 + self.cell)


class Walkable:
    """A walkable area from its rings (their union), for point-in-area tests of many points.

    A grid of ``cell_m`` cells, each known to be inside, outside or on the boundary, answers
    most points by a lookup; only points in boundary cells get the exact (shapely) test."""

    INSIDE, OUTSIDE, EDGE = 1, 0, 2

    def __init__(self, rings: Sequence[Sequence[Sequence[float]]], cell_m: float = 2.0):
        self.geometry = union_of(rings)
        shapely.prepare(self.geometry)
        self._grid = _Grid(self.geometry.bounds, cell_m)
        boxes = self._grid.boxes()
        self._cells = np.where(shapely.contains_properly(self.geometry, boxes), self.INSIDE,
                               np.where(shapely.intersects(self.geometry, boxes), self.EDGE, self.OUTSIDE)).astype(np.int8)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """For points (n, 2): whether each is inside (on the boundary counts as inside)."""
        p = np.asarray(points, float).reshape(-1, 2)
        cell = self._grid.cell_of(*self._grid.ij(p))
        kind = np.where(cell >= 0, self._cells[np.maximum(cell, 0)], self.OUTSIDE)
        out = kind == self.INSIDE
        edge = np.flatnonzero(kind == self.EDGE)
        if len(edge):
            out[edge] = shapely.intersects_xy(self.geometry, p[edge, 0], p[edge, 1])
        return out

    def nearest_inside(self, points: np.ndarray) -> np.ndarray:
        """Points (n, 2) with each one outside moved to the nearest point of the area (a new array;
        points inside are unchanged)."""
        p = np.array(points, float).reshape(-1, 2)
        outside = np.flatnonzero(~self.contains(p))
        if len(outside):
            lines = shapely.shortest_line(self.geometry, shapely.points(p[outside]))
            p[outside] = shapely.get_coordinates(lines)[0::2]  # each line starts on the area
        return p


class WallIndex:
    """Which moves cross a wall, for many walls: a grid of ``cell_m`` cells lists the walls whose
    box meets each cell; a move shorter than a cell meets at most 2 × 2 cells, and
    ``segments_cross`` runs on the walls listed there only (the same rule as
    ``tracking.geometry.crosses_walls``: touching a wall counts, sliding along one does not).
    Longer moves are tested against every wall."""

    def __init__(self, walls: np.ndarray, cell_m: float = 2.0):
        self.walls = np.asarray(walls, float).reshape(-1, 4)
        w = self.walls
        lo = np.minimum(w[:, :2], w[:, 2:])
        hi = np.maximum(w[:, :2], w[:, 2:])
        bounds = [*lo.min(axis=0), *hi.max(axis=0)] if len(w) else [0.0, 0.0, 1.0, 1.0]
        self._grid = g = _Grid(bounds, cell_m)
        i0, j0 = g.ij(lo)
        i1, j1 = g.ij(hi)
        i0, j0 = np.clip(i0, 0, g.nx - 1), np.clip(j0, 0, g.ny - 1)
        i1, j1 = np.clip(i1, 0, g.nx - 1), np.clip(j1, 0, g.ny - 1)
        cells, ids = [], []
        for k in range(len(w)):  # once per plan
            ii, jj = np.meshgrid(np.arange(i0[k], i1[k] + 1), np.arange(j0[k], j1[k] + 1))
            cells.append((jj * g.nx + ii).ravel())
            ids.append(np.full(ii.size, k))
        cell = np.concatenate(cells) if cells else np.zeros(0, np.int64)
        order = np.argsort(cell, kind="stable")
        self._wall_ids = (np.concatenate(ids) if ids else np.zeros(0, np.int64))[order]
        self._ptr = np.searchsorted(cell[order], np.arange(g.nx * g.ny + 1))

    def crosses(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        start = np.asarray(start, float).reshape(-1, 2)
        end = np.asarray(end, float).reshape(-1, 2)
        hit = np.zeros(len(start), dtype=bool)
        if len(self.walls) == 0 or len(start) == 0:
            return hit
        g = self._grid
        i0, j0 = g.ij(np.minimum(start, end))
        i1, j1 = g.ij(np.maximum(start, end))
        long = (i1 - i0 > 1) | (j1 - j0 > 1)
        if long.any():
            hit[long] = crosses_walls(start[long], end[long], self.walls)
        moves, cells = [], []
        for di in (0, 1):
            for dj in (0, 1):
                ok = ~long & (i0 + di <= i1) & (j0 + dj <= j1)
                c = g.cell_of(i0 + di, j0 + dj)
                ok &= c >= 0
                moves.append(np.flatnonzero(ok))
                cells.append(c[ok])
        move = np.concatenate(moves)
        cell = np.concatenate(cells)
        count = self._ptr[cell + 1] - self._ptr[cell]
        total = int(count.sum())
        if total == 0:
            return hit
        move = np.repeat(move, count)
        first = np.repeat(self._ptr[cell] - (np.cumsum(count) - count), count)
        wall = self._wall_ids[first + np.arange(total)]
        cross = segments_cross(start[move], end[move], self.walls[wall])
        hit[move[cross]] = True
        return hit
