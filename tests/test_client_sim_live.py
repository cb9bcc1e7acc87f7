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


def test_survey_then_track_phones_through_sessions(admin, live_server):
    from client_sim.runs import run_track
    from tests.conftest import DEVICE_KEY

    survey = asyncio.run(run_survey(live_server.url, ADMIN_KEY, "open_room", scans_per_heading=2, seed=1, train="knn"))
    assert survey["model"]["status"] == "ready"
    result = asyncio.run(run_track(live_server.url, DEVICE_KEY, "open_room", survey["site_id"], phones=2,
                                   filters=("skpf", "ekf"), seed=4))
    for phone in result["phones"]:
        assert "error" not in phone and phone["failed_posts"] == 0
        batches = phone["batch_estimates"]
        assert [b["t"] for b in batches] == sorted(b["t"] for b in batches)
        track = phone["track"]
        assert track[0]["source"] == "init" and {r["source"] for r in track[1:]} <= {"step", "scan"}
        assert len(track) > len(batches)
        mean = sum(r["error_m"] for r in track) / len(track)
        pdr = sum(r["error_m"] for r in phone["pdr_only"]) / len(phone["pdr_only"])
        assert mean < 3.0 and mean < pdr + 1.0, (phone["filter"], mean, pdr)


def test_crowd_rounds_grow_the_map_from_a_site_without_survey(admin, live_server):
    from client_sim.runs import run_crowd
    from tests.conftest import DEVICE_KEY

    result = asyncio.run(run_crowd(live_server.url, ADMIN_KEY, DEVICE_KEY, "open_room", rounds=2, phones=3,
                                   probes=8, filter="ekf", train="knn", seed=2))
    bootstrap, *rounds = result["rounds"]
    assert bootstrap["model"]["algorithm"] == "propagation" and bootstrap["model"]["status"] == "ready"
    assert bootstrap["site"]["fingerprints"] == {"survey": 0, "crowd": 0}
    assert bootstrap["site"]["settings"]["crowdsourcing"] is True
    crowd = [r["site"]["fingerprints"]["crowd"] for r in rounds]
    assert 0 < crowd[0] <= crowd[1]
    assert all(r["sessions_ok"] == 3 for r in rounds)
    assert rounds[-1]["model"]["status"] == "ready" and rounds[-1]["model"]["active"] is True
    assert rounds[-1]["locate"]["answered"] == 8
