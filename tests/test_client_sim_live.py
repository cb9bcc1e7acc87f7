"""client_sim against a live server over real HTTP."""

from __future__ import annotations

import asyncio

from client_sim.runs import run_survey
from client_sim.world import get_world
from tests.conftest import ADMIN_KEY


def test_survey_creates_the_scenario_site_and_stores_every_scan(admin, live_server):
    world = get_world("open_room")
    result = asyncio.run(run_survey(live_server.url, ADMIN_KEY, world, scans_per_heading=1, seed=3))
    site = admin.get(f"/api/v1/sites/{result['site_id']}").json()
    assert result["accepted"] == result["fingerprints"] == site["fingerprints"]["survey"] > 0
    assert site["reference_points"] == len(world.reference_points)
    assert site["transmitters"] == len(world.transmitters)
    assert [f["level"] for f in site["floors"]] == sorted({f.level for f in world.floors})
    points = admin.get(f"/api/v1/sites/{result['site_id']}/reference-points").json()
    assert {(p["x"], p["y"]) for p in points} == {(x, y) for x, y, _ in world.reference_points}
