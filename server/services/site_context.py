"""What fixes on a site depend on, cached per process and checked against the site's revision.

A tracking batch needs the site's positioned transmitters, its settings, its floors' walls
and walkable areas, the model that serves it and the grid directions that model's survey
showed. Reading those costs more than the rest of a batch, yet they change only on admin
actions, each of which gives the site a new revision
(``Site.revision``). The batch reads the revision with the session row, in the same
statement, so a cached context is used only while it is exactly current: a change made
through any process is seen by the next batch of every process.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from server.db import Database
from server.domain import ServingModel
from server.errors import NotFound
from server.estimation.types import Beacon, SiteMap
from server.services.floorplans import usable_areas
from server.services.lru import Lru
from server.store import floorplans as plan_store
from server.store import models as model_store
from server.store import sites as store


@dataclass(frozen=True)
class SiteContext:
    revision: str
    settings: dict[str, Any]
    #: positioned transmitters, walls, walkable areas and survey grids, as the tracker sees them
    map: SiteMap
    #: the site's active model, when it is ready (a session pinned to a model asks for it)
    active_model: ServingModel | None


class SiteContexts:
    """The latest context of up to ``size`` sites; a site is reloaded when its revision moves."""

    def __init__(self, db: Database, size: int = 256):
        self._db = db
        self._contexts: Lru[int, SiteContext] = Lru(size)

    def get(self, site_id: int, revision: str) -> SiteContext:
        context = self._contexts.get(site_id)
        if context is None or context.revision != revision:
            context = self._load(site_id)
            self._contexts.put(site_id, context)
        return context

    def _load(self, site_id: int) -> SiteContext:
        with self._db.transaction() as s:
            found = store.site_context(s, site_id)
            active = model_store.serving_model(s.connection(), site_id, None)
            walkable = plan_store.walkable_areas(s, site_id)
            grids = {} if active is None else model_store.survey_grids(s, active.model_id)
        if found is None:
            raise NotFound(f"site {site_id} does not exist")
        return SiteContext(
            revision=found.revision,
            settings=dict(found.settings),
            map=SiteMap(
                beacons={
                    t.id: Beacon(t.id, t.x, t.y, t.floor, t.tx_power_dbm, t.path_loss_exponent, t.building)
                    for t in found.transmitters
                    if t.x is not None and t.y is not None
                },
                walls={floor: list(walls) for floor, walls in found.walls.items()},
                walkable=usable_areas(walkable),
                grids=grids,
            ),
            active_model=None if active is None else active.ready(),
        )
