"""The floor's grid measured from the survey, over real HTTP and the real database: a model trained on
walks around a rotated corridor loop reports the loop's direction in ``metrics.survey_grid``, a
lattice survey without devices or times its axes, and the site's context hands the active model's
grid to the sessions (``SiteMap.grids``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.db import Database
from server.services.site_context import SiteContexts
from tests.api.test_models import train
from tests.helpers.synthetic import SyntheticSite, make_site

RADIO = make_site(nx=8, ny=3, spacing_m=4.0, floors=(0,), seed=4)
DEG = 25.0


def loop_walk(every_m: float = 0.7, width: float = 28.0, height: float = 8.0) -> np.ndarray:
    """Points every ``every_m`` around a width × height loop, turned ``DEG`` clockwise."""
    pts = []
    for v in np.arange(0.0, 2 * (width + height), every_m):
        if v < width:
            p = (v, 0.0)
        elif v < width + height:
            p = (width, v - width)
        elif v < 2 * width + height:
            p = (2 * width + height - v, height)
        else:
            p = (0.0, 2 * (width + height) - v)
        pts.append(p)
    xy = np.array(pts)
    c, s = math.cos(math.radians(DEG)), math.sin(math.radians(DEG))
    return np.column_stack((c * xy[:, 0] + s * xy[:, 1], -s * xy[:, 0] + c * xy[:, 1]))


def _site(admin, name: str, rows: list[dict]) -> dict:
    site = admin.post("/api/v1/sites", json={"name": name, "floors": [{"level": 0}],
                                             "transmitters": RADIO.transmitters}).json()
    answer = admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows})
    assert answer.status_code == 201, answer.text
    return site


def walked_rows() -> list[dict]:
    radio = SyntheticSite(transmitters=RADIO.transmitters, rp=[])
    rng = np.random.default_rng(2)
    rows = []
    for lap, device in enumerate(("phone-a", "phone-b")):
        for k, (x, y) in enumerate(loop_walk()):
            rows.append({"x": float(x), "y": float(y), "floor": 0, "device": device, "t": 1000.0 * lap + 0.5 * k,
                         "rss": radio.scan(float(x), float(y), 0, None, rng)})
    return rows


def test_a_model_trained_on_walks_reports_the_floors_grid_and_sessions_get_it(admin, clean_db):
    site = _site(admin, "walked loop", walked_rows())
    model = train(admin, site, algorithm="knn")
    assert model["status"] == "ready" and model["active"]
    (grid,) = model["metrics"]["survey_grid"]
    assert (grid["building"], grid["floor"], grid["source"]) == (0, 0, "walks")
    assert grid["deg"] == pytest.approx(DEG, abs=0.5) and grid["resultant"] > 0.9
    db = Database(clean_db)
    try:  # (a new process's contexts: the first batch loads the site whatever revision it read)
        assert SiteContexts(db).get(site["id"], "first").map.grids == {(0, 0): pytest.approx(DEG, abs=0.5)}
    finally:
        db.dispose()


def test_a_lattice_survey_without_walks_gives_its_axes(admin):
    rows = RADIO.survey(scans_per_rp=4, seed=1).to_rows()
    for row in rows:
        row.pop("building", None)
        row.pop("device", None)
    model = train(admin, _site(admin, "lattice", rows), algorithm="knn")
    (grid,) = model["metrics"]["survey_grid"]
    assert grid["source"] == "points" and grid["deg"] == pytest.approx(0.0, abs=0.25)
