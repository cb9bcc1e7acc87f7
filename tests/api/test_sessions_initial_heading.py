"""``initial.heading_deg`` with the ``heading_std_deg`` extension over real HTTP: a start direction
known independently of the phone's compass turns a self-calibrating tracker's steps from the first
one; ``heading_deg`` alone (the phone's own reading) changes nothing; bad values are 422s naming them."""

from __future__ import annotations

import pytest

from tests.api.test_sessions import site  # noqa: F401  (a fixture)

START = {"x": 1.0, "y": 2.0, "floor": 0}


def _end(device, site_id: int, initial: dict) -> tuple[float, float]:
    """Where an ekf session ends after 10 steps reported at 50° from ``initial``."""
    answer = device.post("/api/v1/sessions", json={"site_id": site_id, "filter": "ekf", "initial": initial})
    assert answer.status_code == 201, answer.text
    sid = answer.json()["id"]
    steps = [{"t": 0.5 * (i + 1), "length_m": 0.7, "heading_deg": 50.0} for i in range(10)]
    answer = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "steps": steps, "scans": []})
    assert answer.status_code == 200, answer.text
    e = answer.json()["estimate"]
    return e["x"], e["y"]


def test_a_start_direction_with_its_sigma_turns_the_track_and_one_without_changes_nothing(device, site):  # noqa: F811
    plain = _end(device, site, START)
    assert _end(device, site, {**START, "heading_deg": 50.0}) == plain  # the phone's own reading: nothing new
    told = _end(device, site, {**START, "heading_deg": 90.0, "heading_std_deg": 2.0})
    # told it walks at 90° (east), the track turns from 50° towards it: further east, less north
    assert told[0] > plain[0] + 1.0 and told[1] < plain[1] - 1.0


@pytest.mark.parametrize("initial, field", [
    ({**START, "heading_std_deg": 2.0}, "initial"),  # a σ without the heading
    ({**START, "heading_deg": 90.0, "heading_std_deg": 0.0}, "heading_std_deg"),
    ({**START, "heading_deg": 90.0, "heading_std_deg": -3.0}, "heading_std_deg"),
    ({**START, "heading_deg": 90.0, "heading_std_deg": 181.0}, "heading_std_deg"),
    ({**START, "heading_deg": 90.0, "heading_std_deg": "two"}, "heading_std_deg"),
])
def test_a_bad_heading_sigma_is_a_422_that_names_it(device, site, initial, field):  # noqa: F811
    answer = device.post("/api/v1/sessions", json={"site_id": site, "filter": "ekf", "initial": initial})
    assert answer.status_code == 422, answer.text
    assert any(field in ".".join(map(str, e["loc"])) and ("heading" in e["msg"] or e["loc"][-1] == field)
               for e in answer.json()["detail"]), answer.text


def test_a_nan_heading_sigma_is_a_422(device, site):  # noqa: F811
    body = (f'{{"site_id": {site}, "filter": "ekf", "initial": {{"x": 1, "y": 2, "floor": 0, "heading_deg": 90, '
            '"heading_std_deg": NaN}}')
    answer = device.post("/api/v1/sessions", content=body, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422, answer.text


def test_the_openapi_schema_documents_the_heading_sigma(anonymous):
    props = anonymous.get("/openapi.json").json()["components"]["schemas"]["InitialIn"]["properties"]
    assert "Extension" in props["heading_std_deg"]["description"]
    assert "heading_std_deg" in props["heading_deg"]["description"]
