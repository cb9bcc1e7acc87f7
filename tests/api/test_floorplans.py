"""PUT /api/v1/sites/{id}/floors/{level}/plan over real HTTP: a lon/lat plan lands as walls and
walkable space in the site frame, a PF session on the floor then stays out of the store, and bad
plans are refused with a 422 naming the problem, changing nothing."""

from __future__ import annotations

import numpy as np
import pytest

from server.estimation.floorplan import Walkable
from tests.helpers.floorplans import HEIGHT_M, WIDTH_M, in_store, plan_geojson

BBOX = {"bbox": {}}  # the floor's own width and height


@pytest.fixture
def site(admin) -> int:
    answer = admin.post("/api/v1/sites", json={"name": "mall", "floors": [
        {"level": 0, "width_m": WIDTH_M, "height_m": HEIGHT_M}, {"level": 1}]})
    assert answer.status_code == 201, answer.text
    return answer.json()["id"]


def put_plan(client, site, body, level=0, **params):
    """``body`` a dict, or JSON text (to send numbers JSON encoders refuse, such as 1e400)."""
    if isinstance(body, str):
        return client.put(f"/api/v1/sites/{site}/floors/{level}/plan", content=body, params=params,
                          headers={"content-type": "application/json"})
    return client.put(f"/api/v1/sites/{site}/floors/{level}/plan", json=body, params=params)


def test_a_plan_lands_on_the_floor_in_site_metres(admin, site):
    answer = put_plan(admin, site, {"geojson": plan_geojson(), "transform": BBOX})
    assert answer.status_code == 200, answer.text
    plan = answer.json()
    (a, b, c), (d, e, f) = plan["matrix"]
    assert a * 120.002 + b * 30.001 + c == pytest.approx(WIDTH_M, abs=1e-6)
    assert d * 120.002 + e * 30.001 + f == pytest.approx(HEIGHT_M, abs=1e-6)
    assert plan["walkable_area_m2"] == pytest.approx(200 * 100 - 100 * 60, rel=1e-6)
    area = Walkable(plan["walkable"])
    assert area.contains(np.array([[10, 10], [100, 20], [100, 70]])).tolist() == [True, True, False]
    floor = next(fl for fl in admin.get(f"/api/v1/sites/{site}").json()["floors"] if fl["level"] == 0)
    assert floor["walls"] == plan["walls"]
    assert floor["walkable"] == plan["walkable"]
    # an explicit matrix (here the same one) gives the same plan; importing again replaces it
    again = put_plan(admin, site, {"geojson": plan_geojson(), "transform": {"matrix": plan["matrix"]}})
    assert again.status_code == 200 and again.json()["walls"] == plan["walls"]


def test_a_pf_session_on_the_floor_stays_out_of_the_store(admin, device, site):
    assert put_plan(admin, site, {"geojson": plan_geojson(), "transform": BBOX}).status_code == 200
    session = device.post("/api/v1/sessions", json={"site_id": site, "filter": "pf", "initial": {
        "x": 30.0, "y": 30.0, "floor": 0, "covariance": [[0.1, 0], [0, 0.1]]}}).json()
    # east along the corridor south of the store, the PDR heading 20° north of east: dead reckoning
    # would enter the store (y > 40 from x ≈ 57 on)
    steps = [{"t": 0.5 * i, "length_m": 0.7, "heading_deg": 70.0, "length_std_m": 0.05, "heading_std_deg": 2.0}
             for i in range(80)]
    for seq in range(8):
        answer = device.post(f"/api/v1/sessions/{session['id']}/batches",
                             json={"seq": seq, "steps": steps[10 * seq:10 * seq + 10], "scans": []})
        assert answer.status_code == 200, answer.text
    track = device.get(f"/api/v1/sessions/{session['id']}/track").json()
    assert len(track) == 81
    assert not any(in_store(e["x"], e["y"]) for e in track)
    assert track[-1]["x"] > 70.0  # it went on east along the corridor


@pytest.mark.parametrize("body, field, message", [
    ({"geojson": {"type": "Point", "coordinates": [0, 0]}, "transform": BBOX}, "geojson", "FeatureCollection"),
    ('{"geojson": {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": '
     '{"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 1e400], [0, 0]]]}}]}, "transform": {"bbox": {}}}',
     "geojson", "non-finite"),
    ({"geojson": plan_geojson(), "transform": {"matrix": [[1, 2, 0], [2, 4, 0]]}}, "transform", "degenerate"),
    ({"geojson": plan_geojson(), "transform": {"matrix": [[1e307, 0, 0], [0, 1, 0]]}}, "transform",
     "non-finite coordinates"),
    ({"geojson": plan_geojson(), "transform": {"matrix": [[1e300, 0, 0], [0, 1e300, 0]]}}, "transform",
     "out of range"),
    # a polygon without area (all its corners one point) gives nothing: refused, not a floor without walls
    ({"geojson": {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": {
        "type": "Polygon", "coordinates": [[[3, 3], [3, 3], [3, 3], [3, 3]]]}}]},
      "transform": {"matrix": [[1, 0, 0], [0, 1, 0]]}}, "geojson", "neither a wall nor a walkable area"),
])
def test_bad_plans_are_422_naming_the_problem(admin, site, snapshot, body, field, message):
    before = snapshot()
    answer = put_plan(admin, site, body)
    assert answer.status_code == 422, answer.text
    detail = answer.json()["detail"][0]
    assert detail["loc"] == ["body", field] and message in detail["msg"]
    assert snapshot() == before


def test_plan_body_and_floor_checks(admin, device, site, snapshot, monkeypatch):
    before = snapshot()
    both = put_plan(admin, site, {"geojson": plan_geojson(), "transform": {"bbox": {}, "matrix": [[1, 0, 0], [0, 1, 0]]}})
    assert both.status_code == 422 and "exactly one" in both.text
    assert put_plan(admin, site, {"geojson": plan_geojson(), "transform": {"matrix": [[1, 0], [0, 1]]}}).status_code == 422
    no_size = put_plan(admin, site, {"geojson": plan_geojson(), "transform": BBOX}, level=1)
    assert no_size.status_code == 422 and "width_m and height_m" in no_size.text
    monkeypatch.setattr("server.estimation.floorplan.MAX_VERTICES", 5)
    big = put_plan(admin, site, {"geojson": plan_geojson(), "transform": BBOX})
    assert big.status_code == 422 and "10 vertices, more than 5" in big.text
    assert put_plan(admin, site, {"geojson": plan_geojson(), "transform": BBOX}, level=7).status_code == 404
    assert put_plan(admin, site, {"geojson": plan_geojson(), "transform": BBOX}, building=3).status_code == 404
    assert put_plan(admin, 99999, {"geojson": plan_geojson(), "transform": BBOX}).status_code == 404
    assert put_plan(device, site, {"geojson": plan_geojson(), "transform": BBOX}).status_code == 403
    assert snapshot() == before
