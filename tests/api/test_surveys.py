"""Survey upload over real HTTP: JSON, CSV, UJIIndoorLoc; every bad-input class leaves the store unchanged."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

FIXTURES = Path(__file__).parent.parent / "fixtures"
AP = "wifi:aa:bb:cc:dd:ee:01"
BEACON = "ble:f7826da6-4fa2-4e98-8024-bc5b71e0893e:1:7"


@pytest.fixture
def site(admin):
    answer = admin.post("/api/v1/sites", json={"name": "Survey site", "floors": [{"level": 0}, {"level": 1}]})
    return answer.json()


def surveys_url(site) -> str:
    return f"/api/v1/sites/{site['id']}/surveys"


def fingerprint(**overrides):
    fp = {"x": 1.0, "y": 2.0, "floor": 0, "rss": {AP: -60.0, BEACON: -75.5}, "heading_deg": 90, "label": "A1"}
    fp.update(overrides)
    return fp


def test_json_survey_is_stored_and_counted(admin, site):
    body = {"fingerprints": [fingerprint(), fingerprint(heading_deg=180), fingerprint(label="B", x=4.0, floor=1)]}
    answer = admin.post(surveys_url(site), json=body)
    assert answer.status_code == 201, answer.text
    assert answer.json()["accepted"] == 3 and answer.json()["reference_points"] == 2
    stored = admin.get(f"/api/v1/sites/{site['id']}").json()
    assert stored["fingerprints"] == {"survey": 3, "crowd": 0}
    assert stored["transmitters"] == 2 and stored["reference_points"] == 2


def test_csv_survey_with_empty_cells_as_not_heard(admin, site):
    csv = (
        f"x,y,floor,heading_deg,label,device,t,{AP},{BEACON}\n"
        "1.5,2.0,0,90,A1,pixel,0.0,-61,\n"
        "1.5,2.0,0,270,A1,pixel,1.0,,-70\n"
        "7,8,1,,,,,-80,-81\n"
    )
    answer = admin.post(surveys_url(site), content=csv, headers={"Content-Type": "text/csv"})
    assert answer.status_code == 201, answer.text
    assert answer.json()["accepted"] == 3 and answer.json()["reference_points"] == 2
    points = {p["label"]: p for p in admin.get(f"/api/v1/sites/{site['id']}/reference-points").json()}
    assert points["A1"]["fingerprints"] == 2 and points[None]["floor"] == 1


def test_ujiindoorloc_format_maps_columns_and_skips_silent_rows(admin):
    site = admin.post("/api/v1/sites", json={"name": "UJI"}).json()
    answer = admin.post(
        f"/api/v1/sites/{site['id']}/surveys?format=ujiindoorloc",
        content=(FIXTURES / "uji_tiny.csv").read_bytes(),
        headers={"Content-Type": "text/csv"},
    )
    assert answer.status_code == 201, answer.text
    result = answer.json()
    assert (result["accepted"], result["skipped"], result["reference_points"]) == (11, 1, 3)
    points = admin.get(f"/api/v1/sites/{site['id']}/reference-points").json()
    assert {(p["floor"], p["x"], p["y"]) for p in points} == {
        (0, -7632.1, 4864982.2), (0, -7640.5, 4864990.0), (1, -7632.1, 4864982.2)
    }
    assert sum(p["fingerprints"] for p in points) == 11
    ids = {t["id"] for t in admin.get(f"/api/v1/sites/{site['id']}/transmitters").json()}
    assert ids and all(i.startswith("wifi:wap0") for i in ids)


def test_dry_run_validates_and_counts_but_stores_nothing(admin, site, snapshot):
    before = snapshot()
    answer = admin.post(surveys_url(site) + "?dry_run=true", json={"fingerprints": [fingerprint()]})
    assert answer.status_code == 200
    assert answer.json()["dry_run"] is True and answer.json()["accepted"] == 1
    assert answer.json()["new_reference_points"] == 1
    assert snapshot() == before


def test_retried_upload_with_same_idempotency_key_is_stored_once(admin, site):
    body = {"fingerprints": [fingerprint(), fingerprint(label="B")]}
    first = admin.post(surveys_url(site), json=body, headers={"Idempotency-Key": "file-1:chunk-0"})
    again = admin.post(surveys_url(site), json=body, headers={"Idempotency-Key": "file-1:chunk-0"})
    assert first.status_code == 201 and again.status_code == 200
    assert again.headers["Idempotent-Replay"] == "true"
    assert again.json() == first.json()
    assert admin.get(f"/api/v1/sites/{site['id']}").json()["fingerprints"]["survey"] == 2


def _bad_json(fp_overrides):
    return {"fingerprints": [fingerprint(), fingerprint(**fp_overrides)]}


@pytest.mark.parametrize(
    "body, field, msg",
    [
        (_bad_json({"rss": {AP: 5.0}}), f"rss.{AP}", "less than or equal to 0"),
        (_bad_json({"rss": {AP: -131.0}}), f"rss.{AP}", "greater than or equal to -130"),
        (_bad_json({"rss": {"WAP001": -50.0}}), "rss.WAP001", "unknown transmitter id format"),
        (_bad_json({"rss": {"ble:F7826DA6": -50.0}}), "rss.ble:F7826DA6", "unknown transmitter id format"),
        (_bad_json({"rss": {}}), "rss", "scan is empty"),
        (_bad_json({"floor": 7}), "floor", "not a floor of this site"),
        (_bad_json({"x": "east"}), "x", "valid number"),
        (_bad_json({"y": None}), "y", "valid number"),
        (_bad_json({"colour": "red"}), "colour", "Extra inputs"),
    ],
)
def test_bad_json_rows_are_422_naming_row_and_field(admin, site, snapshot, body, field, msg):
    before = snapshot()
    answer = admin.post(surveys_url(site), json=body)
    assert answer.status_code == 422, answer.text
    error = answer.json()["detail"][0]
    assert error["row"] == 1 and error["field"] == field and msg in error["msg"]
    assert snapshot() == before


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_nan_and_infinity_are_rejected(admin, site, snapshot, literal):
    before = snapshot()
    raw = '{"fingerprints": [{"x": 1, "y": 2, "floor": 0, "rss": {"wifi:ap1": ' + literal + "}}]}"
    answer = admin.post(surveys_url(site), content=raw, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422
    assert answer.json()["detail"][0]["field"] == "rss.wifi:ap1"
    assert snapshot() == before


def test_malformed_json_is_422(admin, site, snapshot):
    before = snapshot()
    answer = admin.post(surveys_url(site), content=b'{"fingerprints": [', headers={"Content-Type": "application/json"})
    assert answer.status_code == 422 and "malformed JSON" in answer.json()["detail"][0]["msg"]
    assert admin.post(surveys_url(site), json=[1, 2]).status_code == 422
    assert snapshot() == before


def test_csv_errors_name_row_line_and_column(admin, site, snapshot):
    before = snapshot()
    csv = f"x,y,floor,{AP}\n1,2,0,-50\n\n1,2,0,nan\n1,2,0,-20\n"
    answer = admin.post(surveys_url(site), content=csv, headers={"Content-Type": "text/csv"})
    assert answer.status_code == 422
    (error,) = answer.json()["detail"]
    assert (error["row"], error["line"], error["field"]) == (2, 4, f"rss.{AP}")
    bad_header = admin.post(surveys_url(site), content="x,y,floor,AP-1\n1,2,0,-50\n", headers={"Content-Type": "text/csv"})
    assert bad_header.status_code == 422 and bad_header.json()["detail"][0]["field"] == "header.AP-1"
    no_floor = admin.post(surveys_url(site), content="x,y,wifi:a\n1,2,-50\n", headers={"Content-Type": "text/csv"})
    assert "floor" in no_floor.json()["detail"][0]["msg"]
    ragged = admin.post(surveys_url(site), content="x,y,floor,wifi:a\n1,2,0\n", headers={"Content-Type": "text/csv"})
    assert ragged.status_code == 422 and ragged.json()["detail"][0]["line"] == 2
    assert snapshot() == before


def test_ujiindoorloc_errors_name_row_line_and_column(admin, site, snapshot):
    before = snapshot()
    head = "WAP001,LONGITUDE,LATITUDE,FLOOR,PHONEID\n"
    url = surveys_url(site) + "?format=ujiindoorloc"
    bad_cell = admin.post(url, content=head + "-50,1,2,0,13\n-60,east,2,0,13\n", headers={"Content-Type": "text/csv"})
    assert bad_cell.status_code == 422
    (error,) = bad_cell.json()["detail"]
    assert (error["row"], error["line"], error["field"]) == (1, 3, "LONGITUDE")
    no_floor = admin.post(url, content="WAP001,LONGITUDE,LATITUDE\n-50,1,2\n", headers={"Content-Type": "text/csv"})
    assert no_floor.status_code == 422 and "FLOOR" in no_floor.json()["detail"][0]["msg"]
    assert snapshot() == before


def test_one_bad_row_rejects_the_whole_upload(admin, site, snapshot):
    before = snapshot()
    body = {"fingerprints": [fingerprint(label=f"P{i}") for i in range(200)] + [fingerprint(rss={AP: 1.0})]}
    answer = admin.post(surveys_url(site), json=body)
    assert answer.status_code == 422 and answer.json()["detail"][0]["row"] == 200
    assert snapshot() == before


def test_unknown_site_is_404_and_stores_nothing(admin, snapshot):
    before = snapshot()
    answer = admin.post("/api/v1/sites/4242/surveys", json={"fingerprints": [fingerprint()]})
    assert answer.status_code == 404 and "4242" in answer.json()["detail"]
    assert snapshot() == before


def test_empty_survey_and_unsupported_media_type(admin, site):
    assert admin.post(surveys_url(site), json={"fingerprints": []}).status_code == 422
    xml = admin.post(surveys_url(site), content=b"<survey/>", headers={"Content-Type": "application/xml"})
    assert xml.status_code == 415


def test_too_many_rows_is_413(admin, site, snapshot, live_server):
    before = snapshot()
    limit = live_server.app.state.settings.max_survey_rows
    body = {"fingerprints": [fingerprint()] * (limit + 1)}
    answer = admin.post(surveys_url(site), json=body)
    assert answer.status_code == 413 and str(limit) in answer.json()["detail"]
    assert snapshot() == before


def test_too_large_body_is_413_before_parsing(admin, site, snapshot, live_server):
    before = snapshot()
    huge = b'{"fingerprints": [' + b" " * (live_server.app.state.settings.max_body_bytes + 1) + b"]}"
    answer = admin.post(surveys_url(site), content=huge, headers={"Content-Type": "application/json"})
    assert answer.status_code == 413 and "exceeds" in answer.json()["detail"]

    def chunks():  # no Content-Length: the limit must hold on a streamed body too
        for _ in range(live_server.app.state.settings.max_body_bytes // 65536 + 2):
            yield b" " * 65536

    streamed = admin.post(surveys_url(site), content=chunks(), headers={"Content-Type": "application/json"})
    assert streamed.status_code == 413
    assert snapshot() == before
    assert json.loads(admin.get(f"/api/v1/sites/{site['id']}").text)["fingerprints"]["survey"] == 0
