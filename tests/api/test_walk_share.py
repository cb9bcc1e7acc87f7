"""The map's walk share over real HTTP: a model trained on walks (each a device) reports how much
of a fix's error one walk's fixes share; a model held out by reference point has none; an ``ekf``
session may opt in to estimating the walk's fix offset, and a bad value is a 422."""

from __future__ import annotations

from tests.api.test_models import train
from tests.helpers.synthetic import make_site

WALKED = make_site(nx=8, ny=3, spacing_m=4.0, floors=(0,), seed=4)


def _site(admin, walks: bool) -> dict:
    site = admin.post("/api/v1/sites", json={"name": f"Walked {walks}", "floors": [{"level": 0}],
                                             "transmitters": WALKED.transmitters}).json()
    rows = WALKED.survey(scans_per_rp=8, seed=1).to_rows()
    for i, row in enumerate(rows):
        row.pop("building", None)
        if walks:
            row["device"] = f"walk{i % 8}"  # every walk passes every point
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows}).status_code == 201
    return site


def test_a_model_trained_on_walks_reports_its_walk_share(admin):
    walked = train(admin, _site(admin, walks=True), algorithm="knn")
    share = walked["metrics"]["calibration"]["walk_share"]
    assert walked["status"] == "ready" and "every device held out once" in walked["metrics"]["held_out"]
    assert isinstance(share, float) and 0.0 <= share <= 0.9
    points = train(admin, _site(admin, walks=False), algorithm="knn")
    assert points["status"] == "ready" and points["metrics"]["calibration"]["walk_share"] is None


def test_an_ekf_session_opts_in_to_the_walk_offset(admin, device):
    site = _site(admin, walks=False)
    body = {"site_id": site["id"], "filter": "ekf", "initial": {"x": 0.0, "y": 0.0, "floor": 0}}
    opened = device.post("/api/v1/sessions", json={**body, "filter_params": {"walk_offset": 1}})
    assert opened.status_code == 201, opened.text
    assert opened.json()["filter_params"] == {"walk_offset": 1}
    considered = device.post("/api/v1/sessions", json={**body, "filter_params": {"walk_offset": 2}})
    assert considered.status_code == 201 and considered.json()["filter_params"] == {"walk_offset": 2}
    for bad in (3, 0.5):
        refused = device.post("/api/v1/sessions", json={**body, "filter_params": {"walk_offset": bad}})
        assert refused.status_code == 422 and "walk_offset" in refused.text, refused.text
