"""Buildings over real HTTP (extension): a site of two buildings whose floors share levels and
coordinates, told apart building → floor → position by locate and by tracking; v1 bodies without
``building`` are building 0; bad building values are 422; the out-of-coverage flag of locate."""

from __future__ import annotations

import numpy as np
import pytest

from tests.api.test_models import wait_for
from tests.helpers.synthetic import SyntheticSite, make_site

#: two buildings over the same 12 m × 8 m rectangle, each with floors 0 and 1, each with its own
#: transmitters (ids apart), plus one access point both hear (it belongs to neither's map alone)
B0 = make_site(nx=4, ny=3, spacing_m=4.0, floors=(0, 1), seed=2)
B1 = make_site(nx=4, ny=3, spacing_m=4.0, floors=(0, 1), seed=7)
for t in B1.transmitters:
    t["id"] = t["id"].replace(":", ":b1", 1)
SHARED = {"id": "wifi:shared", "kind": "wifi", "floor": 0, "x": 6.0, "y": 4.0, "tx_power_dbm": -40.0,
          "path_loss_exponent": 2.5}
BUILDINGS = {0: B0, 1: B1}
FLOORS = [{"level": level, "building": b} for b in (0, 1) for level in (0, 1)]


def scan(b: int, x: float, y: float, floor: int, rng: np.random.Generator, noise_db: float = 1.0) -> dict[str, float]:
    """A scan in building ``b``: its own transmitters and the shared one."""
    site: SyntheticSite = BUILDINGS[b]
    shared = SyntheticSite(transmitters=[SHARED], rp=[])
    return {**site.scan(x, y, floor, None, rng, noise_db), **shared.scan(x, y, floor, None, rng, noise_db)}


def survey_rows(scans_per_rp: int = 6, seed: int = 1) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [
        {"x": x, "y": y, "floor": f, "building": b, "label": f"b{b}-{label}", "rss": scan(b, x, y, f, rng, 2.0)}
        for b, site in BUILDINGS.items() for label, x, y, f in site.rp for _ in range(scans_per_rp)
    ]


@pytest.fixture
def campus(admin) -> dict:
    transmitters = [{**t, "building": b} for b, site in BUILDINGS.items() for t in site.transmitters] + [SHARED]
    answer = admin.post("/api/v1/sites", json={"name": "Campus", "floors": FLOORS, "transmitters": transmitters})
    assert answer.status_code == 201, answer.text
    site = answer.json()
    answer = admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": survey_rows()})
    assert answer.status_code == 201, answer.text
    return site


def train(admin, site: dict, algorithm: str, activate: bool = True) -> dict:
    answer = admin.post(f"/api/v1/sites/{site['id']}/models", json={"algorithm": algorithm})
    assert answer.status_code == 202, answer.text
    model = wait_for(admin, site["id"], answer.json()["id"])
    assert model["status"] == "ready", model
    if activate:
        assert admin.post(f"/api/v1/sites/{site['id']}/models/{model['id']}/activate").status_code == 200
    return model


def test_floors_transmitters_and_reference_points_keep_their_building(admin, campus):
    site = admin.get(f"/api/v1/sites/{campus['id']}").json()
    assert [(f["building"], f["level"]) for f in site["floors"]] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert site["reference_points"] == 2 * len(B0.rp)  # the same (floor, x, y) in two buildings: two points
    points = admin.get(f"/api/v1/sites/{campus['id']}/reference-points").json()
    assert {(p["building"], p["floor"]) for p in points} == {(0, 0), (0, 1), (1, 0), (1, 1)}
    assert all(p["label"].startswith(f"b{p['building']}-") for p in points)
    tx = {t["id"]: t for t in admin.get(f"/api/v1/sites/{campus['id']}/transmitters").json()}
    assert tx[B1.transmitters[0]["id"]]["building"] == 1 and tx["wifi:shared"]["building"] == 0
    cov = admin.get(f"/api/v1/sites/{campus['id']}/coverage",
                    params={"transmitter": B1.transmitters[0]["id"], "floor": 0, "building": 1}).json()
    assert cov["building"] == 1 and len(cov["reference_points"]) == len(B1.rp) // 2
    assert all(p["heard"] > 0 for p in cov["reference_points"])  # building 0's points never heard it
    other = admin.get(f"/api/v1/sites/{campus['id']}/coverage",
                      params={"transmitter": B1.transmitters[0]["id"], "floor": 0}).json()
    assert other["building"] == 0 and all(p["heard"] == 0 for p in other["reference_points"])


@pytest.mark.parametrize("algorithm", ["wknn", "knn"])
def test_locate_answers_building_then_floor_then_position(admin, device, campus, algorithm):
    """A scan in building 1 is answered in building 1, on a floor of building 1, with candidates of that
    floor only; the same spot in building 0 is answered in building 0."""
    train(admin, campus, algorithm)
    rng = np.random.default_rng(11)
    for b, site in BUILDINGS.items():
        for label, x, y, floor in site.rp[::3]:
            answer = device.post(f"/api/v1/sites/{campus['id']}/locate", json={"rss": scan(b, x, y, floor, rng)})
            assert answer.status_code == 200, answer.text
            fix = answer.json()
            assert (fix["building"], fix["floor"]) == (b, floor), (label, fix)
            assert {(c["building"], c["floor"]) for c in fix["candidates"]} == {(b, floor)}
            assert fix["reference_point"].startswith(f"b{b}-")
            assert np.hypot(fix["x"] - x, fix["y"] - y) < 4.0


def test_tracking_stays_in_the_building_of_its_scans(admin, device, campus):
    """A session walking in building 1 has every estimate in building 1 (live, stored and smoothed)."""
    train(admin, campus, "wknn")
    sid = device.post("/api/v1/sessions", json={"site_id": campus["id"], "filter": "ekf"}).json()["id"]
    rng = np.random.default_rng(3)
    t = 0.0
    for seq, (_, x, y, floor) in enumerate(B1.rp[:6]):
        t += 1.0
        answer = device.post(f"/api/v1/sessions/{sid}/batches", json={
            "seq": seq, "scans": [{"t": t, "rss": scan(1, x, y, floor, rng)}]})
        assert answer.status_code == 200, answer.text
        assert answer.json()["estimate"]["building"] == 1
    for smoothed in ("false", "true"):
        track = device.get(f"/api/v1/sessions/{sid}/track", params={"smoothed": smoothed}).json()
        assert len(track) == 6 and {e["building"] for e in track} == {1}
    assert device.get(f"/api/v1/sessions/{sid}").json()["estimate"]["building"] == 1


def test_a_session_may_start_on_a_floor_of_another_building(device, campus):
    opened = device.post("/api/v1/sessions", json={
        "site_id": campus["id"], "filter": "kf", "initial": {"x": 1.0, "y": 2.0, "floor": 1, "building": 1}})
    assert opened.status_code == 201, opened.text
    assert opened.json()["estimate"]["building"] == 1 and opened.json()["estimate"]["floor"] == 1
    missing = device.post("/api/v1/sessions", json={
        "site_id": campus["id"], "filter": "kf", "initial": {"x": 1.0, "y": 2.0, "floor": 1, "building": 2}})
    assert missing.status_code == 422 and "building 2" in missing.text


def test_v1_bodies_without_building_are_building_0(admin, device):
    """A site, survey, model, locate and session that never say ``building`` work as before and are
    answered with building 0."""
    site = admin.post("/api/v1/sites", json={"name": "v1", "floors": [{"level": 0}, {"level": 1}],
                                             "transmitters": B0.transmitters}).json()
    assert [f["building"] for f in site["floors"]] == [0, 0]
    rows = B0.survey(scans_per_rp=6, seed=1).to_rows()
    assert not any("building" in r for r in rows)
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows}).status_code == 201
    train(admin, site, "wknn", activate=False)
    _, x, y, floor = B0.rp[5]
    fix = device.post(f"/api/v1/sites/{site['id']}/locate",
                      json={"rss": B0.scan(x, y, floor, None, np.random.default_rng(2), 1.0)}).json()
    assert fix["building"] == 0 and fix["floor"] == floor
    opened = device.post("/api/v1/sessions", json={"site_id": site["id"], "filter": "kf",
                                                     "initial": {"x": 0.0, "y": 0.0, "floor": 0}})
    assert opened.status_code == 201 and opened.json()["estimate"]["building"] == 0


def test_ujiindoorloc_keeps_buildingid(admin):
    """The same floor and spot in two buildings of a UJIIndoorLoc file are two reference points."""
    header = "WAP001,WAP002,LONGITUDE,LATITUDE,FLOOR,BUILDINGID,SPACEID,RELATIVEPOSITION,USERID,PHONEID,TIMESTAMP\n"
    rows = "".join(f"-60,-70,-7632.1,4864982.2,2,{b},101,2,1,13,1371713733\n" for b in (0, 1, 2, 1))
    site = admin.post("/api/v1/sites", json={"name": "UJI campus"}).json()
    answer = admin.post(f"/api/v1/sites/{site['id']}/surveys?format=ujiindoorloc", content=header + rows,
                        headers={"Content-Type": "text/csv"})
    assert answer.status_code == 201, answer.text
    assert answer.json()["reference_points"] == 3
    points = admin.get(f"/api/v1/sites/{site['id']}/reference-points").json()
    assert sorted((p["building"], p["floor"], p["fingerprints"]) for p in points) == [(0, 2, 1), (1, 2, 2), (2, 2, 1)]


def test_a_csv_survey_takes_a_building_column(admin, campus):
    csv = "x,y,floor,building,wifi:shared\n1,1,0,1,-60\n1,1,0,,-61\n"
    answer = admin.post(f"/api/v1/sites/{campus['id']}/surveys", content=csv, headers={"Content-Type": "text/csv"})
    assert answer.status_code == 201, answer.text
    assert answer.json()["new_reference_points"] == 2  # (1, 0, 1, 1) and (0, 0, 1, 1): building 0 by default


BAD_BUILDINGS = [-1, 1000, 2**40, 1.5, "one", True, None]


@pytest.mark.parametrize("value", BAD_BUILDINGS)
def test_bad_building_values_are_422_and_change_nothing(admin, device, campus, snapshot, value):
    before = snapshot()
    fp = {"x": 1.0, "y": 1.0, "floor": 0, "building": value, "rss": {"wifi:shared": -60.0}}
    answer = admin.post(f"/api/v1/sites/{campus['id']}/surveys", json={"fingerprints": [fp]})
    assert answer.status_code == 422, answer.text
    assert "building" in answer.text
    site = admin.post("/api/v1/sites", json={"name": "bad", "floors": [{"level": 0, "building": value}]})
    assert site.status_code == 422 and "building" in site.text
    opened = device.post("/api/v1/sessions", json={
        "site_id": campus["id"], "filter": "kf", "initial": {"x": 0.0, "y": 0.0, "floor": 0, "building": value}})
    assert opened.status_code == 422 and "building" in opened.text
    if value is not None:  # a transmitter's building may be null: then it is the floor's default, 0
        tx = admin.put(f"/api/v1/sites/{campus['id']}/transmitters",
                       json=[{"id": "wifi:new", "kind": "wifi", "floor": 0, "building": value}])
        assert tx.status_code == 422 and "building" in tx.text
    assert snapshot() == before


def test_other_building_mistakes_are_422(admin, campus, snapshot):
    before = snapshot()
    twice = admin.post("/api/v1/sites", json={"name": "dup", "floors": [{"level": 0, "building": 1}] * 2})
    assert twice.status_code == 422 and "unique within a building" in twice.text
    undeclared = admin.post(f"/api/v1/sites/{campus['id']}/surveys", json={"fingerprints": [
        {"x": 1.0, "y": 1.0, "floor": 0, "building": 3, "rss": {"wifi:shared": -60.0}}]})
    assert undeclared.status_code == 422 and "building 3 floor 0 is not a floor of this site" in undeclared.text
    no_floor = admin.put(f"/api/v1/sites/{campus['id']}/transmitters",
                         json=[{"id": "wifi:new", "kind": "wifi", "building": 1}])
    assert no_floor.status_code == 422 and "only with a floor" in no_floor.text
    bad_query = admin.get(f"/api/v1/sites/{campus['id']}/coverage",
                          params={"transmitter": "wifi:shared", "floor": 0, "building": -1})
    assert bad_query.status_code == 422
    assert snapshot() == before


def test_walkable_polygons_round_trip_and_bad_ones_are_422(admin):
    ring = [[0.0, 0.0], [10.0, 0.0], [10.0, 5.0], [0.0, 5.0]]
    site = admin.post("/api/v1/sites", json={"name": "w", "floors": [{"level": 0, "walkable": [ring]}, {"level": 1}]})
    assert site.status_code == 201, site.text
    assert [f["walkable"] for f in site.json()["floors"]] == [[ring], None]
    for bad in ([[[0, 0], [1, 1]]], [[[0, 0], [1, 1], ["nan", 0]]], [[[0, 0], [1, 1], [1e9, 0]]], [ring * 30_000]):
        answer = admin.post("/api/v1/sites", json={"name": "bad", "floors": [{"level": 0, "walkable": bad}]})
        assert answer.status_code == 422 and "walkable" in answer.text


def test_locate_flags_a_scan_that_resembles_nothing_surveyed(admin, device, campus):
    """wknn (and knn, its search with k fixed) says whether a scan is in coverage: scans at surveyed spots
    are, a scan hearing both buildings' transmitters loudly at once (no place hears that) is not; models
    that cannot tell answer null."""
    wknn = train(admin, campus, "wknn")
    rng = np.random.default_rng(21)
    url = f"/api/v1/sites/{campus['id']}/locate"
    for b, site in BUILDINGS.items():
        for _, x, y, floor in site.rp[::2]:
            fix = device.post(url, json={"rss": scan(b, x, y, floor, rng)}).json()
            assert fix["in_coverage"] is True and 0 <= fix["coverage_ratio"] <= 1, fix
    nowhere = {t["id"]: -35.0 for site in BUILDINGS.values() for t in site.transmitters}
    fix = device.post(url, json={"rss": nowhere}).json()
    assert fix["in_coverage"] is False and fix["coverage_ratio"] > 1, fix
    knn = train(admin, campus, "knn", activate=False)  # wknn's search with k fixed: it can tell too
    fix = device.post(url, json={"rss": nowhere, "model_id": knn["id"]}).json()
    assert fix["in_coverage"] is False and fix["coverage_ratio"] > 1, fix
    nbc = train(admin, campus, "nbc", activate=False)
    fix = device.post(url, json={"rss": nowhere, "model_id": nbc["id"]}).json()
    assert fix["in_coverage"] is None and fix["coverage_ratio"] is None
    assert device.post(url, json={"rss": nowhere, "model_id": wknn["id"]}).json()["in_coverage"] is False
