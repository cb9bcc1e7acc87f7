"""A floor's plan as stored: its walls and walkable area (``floors.walls`` / ``floors.walkable``)."""

from __future__ import annotations

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from server.store._results import changed, first, tuples
from server.store.sites import touch_site
from server.tables import Floor as FloorRow

#: a floor on its site: (building, level)
FloorKey = tuple[int, int]


def floor_size(s: Session, site_id: int, key: FloorKey) -> tuple[float | None, float | None] | None:
    """The floor's (width_m, height_m), or None when the site has no such floor."""
    building, level = key
    row = first(s.execute(select(FloorRow.width_m, FloorRow.height_m).where(
        FloorRow.site_id == site_id, FloorRow.building == building, FloorRow.level == level)))
    return None if row is None else (row[0], row[1])


def save_plan(s: Session, site_id: int, key: FloorKey, walls: list[list[float]],
              walkable: list[list[list[float]]] | None) -> bool:
    """Replace the floor's walls and walkable area and renew the site's revision (sessions read the
    new plan on their next batch); False when the site has no such floor."""
    building, level = key
    done = s.execute(update(FloorRow).where(
        FloorRow.site_id == site_id, FloorRow.building == building, FloorRow.level == level,
    ).values(walls=walls, walkable=walkable).execution_options(synchronize_session=False))
    if changed(done) != 1:
        return False
    touch_site(s, site_id)
    return True


def walkable_areas(s: Session, site_id: int) -> dict[FloorKey, list[list[list[float]]]]:
    """The walkable rings of every floor of the site that has them."""
    rows = s.execute(select(FloorRow.building, FloorRow.level, FloorRow.walkable).where(FloorRow.site_id == site_id))
    return {(building, level): rings for building, level, rings in tuples(rows) if rings}
