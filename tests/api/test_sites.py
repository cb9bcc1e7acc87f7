"""Sites, floors, transmitters and reference points over real HTTP."""

from __future__ import annotations

import json

import pytest
from sqlalchemy import insert

from server.db import Database
from server.tables import Fingerprint

WALLS = [[0, 0, 10, 0], [10, 0, 10, 8]]
SITE = {
    "name": "Lab",
    "floors": [{"level": 0, "name": "ground", "width_m": 20, "height_m": 10, "walls": WALLS}, {"level": 1}],
    "transmitters": [
        {"id": "wifi:aa:bb:cc:dd:ee:01", "kind": "wifi", "floor": 0, "x": 1.0, "y": 2.0},
        {"id": "ble:f7826da6-4fa2-4e98-8024-bc5b71e0893e:1:7", "kind": "ble", "tx_power_dbm": -59},
    ],
}


def test_create_get_list_delete_site(admin):
    created = admin.post("/api/v1/sites", json=SITE)
    assert created.status_code == 201, created.text
    site = created.json()
    assert site["name"] == "Lab"
    assert [f["level"] for f in site["floors"]] == [0, 1]
    assert site["floors"][0]["walls"] == WALLS
    assert site["transmitters"] == 2
    assert site["fingerprints"] == {"survey": 0, "crowd": 0}

    assert admin.get(f"/api/v1/sites/{site['id']}").json()["name"] == "Lab"
    assert [s["id"] for s in admin.get("/api/v1/sites").json()] == [site["id"]]

    assert admin.delete(f"/api/v1/sites/{site['id']}").status_code == 204
    assert admin.get(f"/api/v1/sites/{site['id']}").status_code == 404
    assert admin.delete(f"/api/v1/sites/{site['id']}").status_code == 404


def test_delete_site_removes_its_fingerprints(admin, snapshot):
    site = admin.post("/api/v1/sites", json={"name": "Gone"}).json()
    survey = {"fingerprints": [{"x": 1, "y": 1, "floor": 0, "rss": {"wifi:ap1": -60}}]}
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json=survey).status_code == 201
    assert admin.delete(f"/api/v1/sites/{site['id']}").status_code == 204
    rows = snapshot()
    assert rows["fingerprints"] == [] and rows["reference_points"] == [] and rows["transmitters"] == []


def test_duplicate_site_name_is_409(admin, snapshot):
    assert admin.post("/api/v1/sites", json={"name": "Twice"}).status_code == 201
    before = snapshot()
    again = admin.post("/api/v1/sites", json={"name": "Twice"})
    assert again.status_code == 409
    assert "Twice" in again.json()["detail"]
    assert snapshot() == before


def test_put_transmitters_upserts_by_id(admin):
    site = admin.post("/api/v1/sites", json=SITE).json()
    url = f"/api/v1/sites/{site['id']}/transmitters"
    answer = admin.put(
        url,
        json=[
            {"id": "wifi:aa:bb:cc:dd:ee:01", "kind": "wifi", "floor": 1, "x": 5.0, "y": 6.0, "path_loss_exponent": 2.2},
            {"id": "wifi:new-ap", "kind": "wifi"},
        ],
    )
    assert answer.status_code == 200, answer.text
    by_id = {t["id"]: t for t in answer.json()}
    assert set(by_id) == {"wifi:aa:bb:cc:dd:ee:01", "ble:f7826da6-4fa2-4e98-8024-bc5b71e0893e:1:7", "wifi:new-ap"}
    assert (by_id["wifi:aa:bb:cc:dd:ee:01"]["x"], by_id["wifi:aa:bb:cc:dd:ee:01"]["floor"]) == (5.0, 1)
    assert by_id["wifi:aa:bb:cc:dd:ee:01"]["path_loss_exponent"] == 2.2
    assert admin.get(f"/api/v1/sites/{site['id']}").json()["transmitters"] == 3


@pytest.mark.parametrize(
    "body, field",
    [
        ({"name": ""}, "name"),
        ({"name": "x", "floors": [{"level": 0}, {"level": 0}]}, "unique"),
        ({"name": "x", "floors": [{"level": 0, "walls": [[0, 0, 1]]}]}, "floors.0.walls.0"),
        ({"name": "x", "transmitters": [{"id": "WIFI:AP", "kind": "wifi"}]}, "transmitters.0.id"),
        ({"name": "x", "transmitters": [{"id": "wifi:ap", "kind": "ble"}]}, "does not match kind"),
        ({"name": "x", "transmitters": [{"id": "wifi:ap", "kind": "wifi", "x": 1}]}, "both x and y"),
        ({"name": "x", "unknown": 1}, "unknown"),
        ({"name": "x", "floors": [{"level": 0}], "transmitters": [{"id": "wifi:ap", "kind": "wifi", "floor": 2}]},
         "does not declare"),
        ({"name": "x", "transmitters": [{"id": "wifi:ap", "kind": "wifi", "x": float("nan"), "y": 1}]}, "x"),
    ],
)
def test_invalid_site_is_422_naming_the_problem(admin, snapshot, body, field):
    before = snapshot()
    raw = json.dumps(body)  # allows NaN, which httpx's json= refuses to send
    answer = admin.post("/api/v1/sites", content=raw, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422
    assert field in answer.text
    assert snapshot() == before


def test_put_transmitters_rejects_bad_rows_and_stores_nothing(admin, snapshot):
    site = admin.post("/api/v1/sites", json=SITE).json()
    before = snapshot()
    url = f"/api/v1/sites/{site['id']}/transmitters"
    ok = {"id": "wifi:fine", "kind": "wifi"}
    for body, field in [
        ([ok, {"id": "wifi:aa:bb", "kind": "wifi", "tx_power_dbm": 99}], "1.tx_power_dbm"),
        ([ok, {"id": "ble:Upper", "kind": "ble"}], "1.id"),
        ([ok, {"id": "wifi:ap9", "kind": "wifi", "floor": 5}], "does not declare"),
        ([ok, ok], "unique"),
    ]:
        answer = admin.put(url, json=body)
        assert answer.status_code == 422 and field in answer.text, answer.text
    assert snapshot() == before


def test_transmitters_of_unknown_site_is_404(admin):
    assert admin.put("/api/v1/sites/999/transmitters", json=[]).status_code == 404
    assert admin.get("/api/v1/sites/999/reference-points").status_code == 404


def test_reference_points_group_by_label_or_position(admin):
    site = admin.post("/api/v1/sites", json={"name": "RP"}).json()
    survey = {
        "fingerprints": [
            {"x": 1, "y": 1, "floor": 0, "rss": {"wifi:ap1": -60}, "label": "A"},
            {"x": 3, "y": 1, "floor": 0, "rss": {"wifi:ap1": -62}, "label": "A"},
            {"x": 5, "y": 5, "floor": 0, "rss": {"wifi:ap1": -70}},
            {"x": 5, "y": 5, "floor": 0, "rss": {"wifi:ap1": -71}},
            {"x": 5, "y": 5, "floor": 1, "rss": {"wifi:ap1": -80}},
        ]
    }
    answer = admin.post(f"/api/v1/sites/{site['id']}/surveys", json=survey)
    assert answer.json() == {
        "accepted": 5, "reference_points": 3, "new_reference_points": 3, "skipped": 0, "already_stored": 0, "dry_run": False,
    }
    points = admin.get(f"/api/v1/sites/{site['id']}/reference-points").json()
    seen = sorted([(p["floor"], p["label"], p["x"], p["y"], p["fingerprints"]) for p in points], key=str)
    assert seen == sorted([(0, "A", 2.0, 1.0, 2), (0, None, 5.0, 5.0, 2), (1, None, 5.0, 5.0, 1)], key=str)


def test_coverage_is_the_measured_rss_per_reference_point(admin):
    site = admin.post("/api/v1/sites", json={"name": "Coverage"}).json()
    ap, other = "wifi:aa:bb:cc:dd:ee:01", "wifi:ap2"
    survey = {
        "fingerprints": [
            {"x": 1, "y": 1, "floor": 0, "rss": {ap: -60, other: -80}, "label": "A"},
            {"x": 3, "y": 1, "floor": 0, "rss": {ap: -63.5}, "label": "A"},
            {"x": 3, "y": 1, "floor": 0, "rss": {other: -75}, "label": "A"},
            {"x": 5, "y": 5, "floor": 0, "rss": {other: -70}},
            {"x": 5, "y": 5, "floor": 1, "rss": {ap: -90}},
        ]
    }
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json=survey).status_code == 201
    answer = admin.get(f"/api/v1/sites/{site['id']}/coverage", params={"transmitter": ap, "floor": 0})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["transmitter"] == ap and body["floor"] == 0
    points = sorted(body["reference_points"], key=lambda p: p["x"])
    assert [(p["label"], p["fingerprints"], p["heard"]) for p in points] == [("A", 3, 2), (None, 1, 0)]
    assert points[0]["mean_rss_dbm"] == pytest.approx((-60 - 63.5) / 2)
    assert (points[0]["x"], points[0]["y"]) == (pytest.approx(7 / 3), 1.0)
    assert points[1]["mean_rss_dbm"] is None and (points[1]["x"], points[1]["y"]) == (5.0, 5.0)
    assert body["crowd"] == {"fingerprints": 0, "heard": 0, "mean_rss_dbm": None}

    upstairs = admin.get(f"/api/v1/sites/{site['id']}/coverage", params={"transmitter": ap, "floor": 1}).json()
    assert [(p["heard"], p["mean_rss_dbm"]) for p in upstairs["reference_points"]] == [(1, -90.0)]
    never = admin.get(f"/api/v1/sites/{site['id']}/coverage", params={"transmitter": "wifi:nobody", "floor": 0})
    assert [p["heard"] for p in never.json()["reference_points"]] == [0, 0]


def test_coverage_params_and_site(admin, device):
    site = admin.post("/api/v1/sites", json={"name": "Coverage params"}).json()
    url = f"/api/v1/sites/{site['id']}/coverage"
    assert admin.get("/api/v1/sites/999/coverage", params={"transmitter": "wifi:ap1", "floor": 0}).status_code == 404
    for params in ({"floor": 0}, {"transmitter": "wifi:ap1"}, {"transmitter": "WIFI:AP1", "floor": 0},
                   {"transmitter": "wifi:ap1", "floor": "one"}, {"transmitter": 'wifi:a"b', "floor": 0}):
        answer = admin.get(url, params=params)
        assert answer.status_code == 422, (params, answer.text)
    assert device.get(url, params={"transmitter": "wifi:ap1", "floor": 0}).status_code == 403
    empty = admin.get(url, params={"transmitter": "wifi:ap1", "floor": 0}).json()
    assert empty["reference_points"] == [] and empty["crowd"]["fingerprints"] == 0


@pytest.mark.parametrize("tx", ["wifi:a.b-c_d", "ble:x", "wifi:wap001", "ble:f7826da6-4fa2-4e98-8024-bc5b71e0893e:1:65535"])
def test_coverage_reads_any_transmitter_id_form(admin, tx):
    site = admin.post("/api/v1/sites", json={"name": f"Coverage {tx}"}).json()
    fps = [{"x": 0, "y": 0, "floor": 0, "rss": {tx: -51.5, "wifi:zz": -60}}, {"x": 0, "y": 0, "floor": 0, "rss": {tx: -52.5}}]
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": fps}).status_code == 201
    body = admin.get(f"/api/v1/sites/{site['id']}/coverage", params={"transmitter": tx, "floor": 0}).json()
    assert [(p["fingerprints"], p["heard"], p["mean_rss_dbm"]) for p in body["reference_points"]] == [(2, 2, -52.0)]


def test_coverage_counts_the_floors_crowd_fingerprints_apart(admin, clean_db):
    site = admin.post("/api/v1/sites", json={"name": "Coverage crowd"}).json()
    survey = {"fingerprints": [{"x": 1, "y": 1, "floor": 0, "rss": {"wifi:ap1": -50}, "label": "A"}]}
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json=survey).status_code == 201
    db = Database(clean_db)
    try:
        with db.transaction() as s:
            s.execute(insert(Fingerprint), [
                {"site_id": site["id"], "source": "crowd", "floor": floor, "x": 2.0, "y": 2.0, "rss": rss, "samples": 1}
                for floor, rss in [(0, {"wifi:ap1": -60.0}), (0, {"wifi:ap1": -70.0}), (0, {"wifi:ap2": -40.0}),
                                   (1, {"wifi:ap1": -90.0})]
            ])
    finally:
        db.dispose()
    body = admin.get(f"/api/v1/sites/{site['id']}/coverage", params={"transmitter": "wifi:ap1", "floor": 0}).json()
    assert [(p["label"], p["fingerprints"], p["heard"], p["mean_rss_dbm"]) for p in body["reference_points"]] == [
        ("A", 1, 1, -50.0)
    ]
    assert body["crowd"] == {"fingerprints": 3, "heard": 2, "mean_rss_dbm": -65.0}
