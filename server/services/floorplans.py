"""Floor plans: a GeoJSON plan imported onto a floor as its walls and walkable area.

The geometry is ``server.estimation.floorplan``'s; this service finds the floor, turns the
plan into the site frame and stores the result (``store.floorplans``). The site's revision is
renewed, so every session's next batch sees the plan (walls reach a tracker when a session
starts or changes floor; the walkable area reaches a PF before every input).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from server.db import Database
from server.errors import InvalidField, NotFound
from server.estimation.floorplan import PlanError, Transform, Walkable, read_plan
from server.store import floorplans as store
from server.store.sites import site_exists


@dataclass(frozen=True)
class PlanTransform:
    """Into the site frame: an explicit 2×3 ``matrix``, or (``matrix`` None) the plan's bounding
    box onto [0, width_m] × [0, height_m], each defaulting to the floor's own size."""

    matrix: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    width_m: float | None = None
    height_m: float | None = None


@dataclass(frozen=True)
class ImportedPlan:
    """What an import stored: the transform used, the walls and the walkable rings (site frame)."""

    building: int
    level: int
    matrix: tuple[tuple[float, float, float], tuple[float, float, float]]
    walls: tuple[tuple[float, float, float, float], ...]
    walkable: tuple[tuple[tuple[float, float], ...], ...] | None
    walkable_area_m2: float | None


class FloorPlanService:
    def __init__(self, db: Database):
        self._db = db

    def import_plan(self, site_id: int, building: int, level: int, geojson: Any, transform: PlanTransform) -> ImportedPlan:
        """Replace the floor's walls and walkable area by the plan's. ``NotFound`` without the site or
        floor; ``InvalidField`` naming ``geojson`` or ``transform`` when the plan cannot be used."""
        key = (building, level)
        with self._db.transaction() as s:
            if not site_exists(s, site_id):
                raise NotFound(f"site {site_id} does not exist")
            size = store.floor_size(s, site_id, key)
        if size is None:
            raise NotFound(f"site {site_id} has no floor {level} in building {building}")
        matrix = _matrix(transform)
        try:
            bbox = None if matrix is not None else _bbox_size(transform, size)
            plan = read_plan(geojson, None if matrix is None else Transform(matrix), bbox_size=bbox)
            area = None if plan.walkable is None else float(Walkable(plan.walkable).geometry.area)
        except PlanError as exc:
            raise InvalidField(exc.part, str(exc)) from None
        walls = [[round(float(v), 4) for v in w] for w in plan.walls]
        with self._db.transaction(write=True) as s:
            if not store.save_plan(s, site_id, key, walls, plan.walkable):
                raise NotFound(f"site {site_id} has no floor {level} in building {building}")
        used = matrix if matrix is not None else plan.transform.matrix
        return ImportedPlan(
            building=building, level=level, matrix=used,
            walls=tuple((w[0], w[1], w[2], w[3]) for w in walls),
            walkable=None if plan.walkable is None else tuple(tuple((p[0], p[1]) for p in r) for r in plan.walkable),
            walkable_area_m2=area,
        )


def _matrix(transform: PlanTransform):
    if transform.matrix is None:
        return None
    try:
        Transform(transform.matrix)
    except PlanError as exc:
        raise InvalidField("transform", str(exc)) from None
    return transform.matrix


def _bbox_size(transform: PlanTransform, floor_size: tuple[float | None, float | None]) -> tuple[float, float]:
    width = transform.width_m if transform.width_m is not None else floor_size[0]
    height = transform.height_m if transform.height_m is not None else floor_size[1]
    if width is None or height is None:
        raise InvalidField("transform", "a bbox transform needs width_m and height_m: give them, or declare "
                                        "them on the floor")
    return float(width), float(height)


def usable_areas(stored: dict[tuple[int, int], Any]) -> dict[tuple[int, int], Walkable]:
    """Stored walkable rings as ``Walkable`` areas for the trackers; a floor whose rings enclose
    nothing usable (possible through ``FloorIn.walkable``) is left unconstrained rather than failing
    every batch."""
    out = {}
    for key, rings in stored.items():
        try:
            out[key] = Walkable(rings)
        except (PlanError, ValueError, TypeError):
            continue
    return out
