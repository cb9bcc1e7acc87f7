"""Floor plans (admin, extension): import a GeoJSON plan as a floor's walls and walkable area."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request
from pydantic import BaseModel, Field, model_validator

from server.api.deps import Admin, PathId
from server.schemas import Strict
from server.services.floorplans import FloorPlanService, ImportedPlan, PlanTransform

router = APIRouter(prefix="/api/v1/sites", tags=["sites"])

Finite = Annotated[float, Field(allow_inf_nan=False)]
Size = Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)]
LevelPath = Annotated[int, Path(ge=-20, le=200, description="Floor level.")]
BuildingQuery = Annotated[int, Query(ge=0, le=999, description="The floor's building (0 on a site of one building).")]


class BBoxIn(Strict):
    """The plan's bounding box onto [0, width_m] × [0, height_m]; each defaults to the floor's."""

    width_m: Size | None = None
    height_m: Size | None = None


class PlanTransformIn(Strict):
    """Exactly one of ``matrix`` and ``bbox``."""

    matrix: Annotated[list[Annotated[list[Finite], Field(min_length=3, max_length=3)]],
                      Field(min_length=2, max_length=2, description=(
                          "[[a, b, c], [d, e, f]]: x' = a·x + b·y + c, y' = d·x + e·y + f (site metres)."))] | None = None
    bbox: BBoxIn | None = Field(None, description=(
        "Map the plan's bounding box onto [0, width_m] × [0, height_m] (the MSFT competition's convention)."))

    @model_validator(mode="after")
    def _one(self) -> PlanTransformIn:
        if (self.matrix is None) == (self.bbox is None):
            raise ValueError("give exactly one of 'matrix' and 'bbox'")
        return self


class FloorPlanIn(Strict):
    geojson: dict[str, Any] = Field(description=(
        "A GeoJSON FeatureCollection. Polygons whose properties.type or .category is 'floor' are walkable; "
        "other polygons are obstacles (stores, rooms without a door in the plan); lines are walls; points "
        "are ignored. At most 100,000 vertices."))
    transform: PlanTransformIn


class FloorPlanOut(BaseModel):
    building: int
    level: int
    matrix: list[list[float]] = Field(description="The transform used, [[a, b, c], [d, e, f]].")
    walls: list[list[float]] = Field(description="The floor's walls now: the walkable area's boundary and line features.")
    walkable: list[list[list[float]]] | None = Field(description=(
        "The floor's walkable area now: polygons (exterior rings) whose union it is; null when the plan has no "
        "floor outline."))
    walkable_area_m2: float | None


async def floorplan_service(request: Request) -> FloorPlanService:
    return request.app.state.floorplans


FloorPlans = Annotated[FloorPlanService, Depends(floorplan_service)]


def _out(plan: ImportedPlan) -> FloorPlanOut:
    return FloorPlanOut(
        building=plan.building, level=plan.level, matrix=[list(row) for row in plan.matrix],
        walls=[list(w) for w in plan.walls],
        walkable=None if plan.walkable is None else [[list(p) for p in ring] for ring in plan.walkable],
        walkable_area_m2=None if plan.walkable_area_m2 is None else round(plan.walkable_area_m2, 3),
    )


@router.put("/{site_id}/floors/{level}/plan", response_model=FloorPlanOut)
def put_floor_plan(
    site_id: PathId, level: LevelPath, body: FloorPlanIn, plans: FloorPlans, _: Admin,
    building: BuildingQuery = 0,
) -> FloorPlanOut:
    """Replace the floor's walls and walkable area by those of a GeoJSON plan (extension). The PF of
    every session on the floor then kills particles that cross a wall or leave walkable space."""
    t = body.transform
    transform = PlanTransform(
        matrix=None if t.matrix is None else (
            (t.matrix[0][0], t.matrix[0][1], t.matrix[0][2]), (t.matrix[1][0], t.matrix[1][1], t.matrix[1][2])),
        width_m=None if t.bbox is None else t.bbox.width_m, height_m=None if t.bbox is None else t.bbox.height_m,
    )
    return _out(plans.import_plan(site_id, building, level, body.geojson, transform))
