"""The dashboard's held-out error layer: the active model's mean error per held-out reference
point, drawn on the floor map with its legend (a demo-like synthetic site, trained over HTTP)."""

from __future__ import annotations

import pytest

from tests.api.test_models import wait_for
from tests.browser.test_dashboard import login
from tests.conftest import ADMIN_KEY
from tests.helpers.synthetic import make_site

pytestmark = pytest.mark.browser

SYNTH = make_site(nx=5, ny=4, spacing_m=3.0, floors=(0, 1), seed=4)


def test_held_out_error_layer_shows_the_active_models_points(page, live_server, admin):
    site = admin.post("/api/v1/sites", json={"name": "demo-like", "floors": [{"level": 0}, {"level": 1}],
                                             "transmitters": SYNTH.transmitters}).json()
    rows = SYNTH.survey(scans_per_rp=6, seed=1).to_rows()
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows}).status_code == 201
    queued = admin.post(f"/api/v1/sites/{site['id']}/models", json={"algorithm": "knn"}).json()
    model = wait_for(admin, site["id"], queued["id"])
    assert model["status"] == "ready" and model["active"], model
    points = admin.get(f"/api/v1/sites/{site['id']}/models/{model['id']}/errors").json()
    on_ground = {p["label"]: p for p in points if p["floor"] == 0}
    assert on_ground

    login(page, live_server.url, ADMIN_KEY)
    page.wait_for_selector("circle.rp")
    assert not page.locator("#errors-layer").count() and not page.locator("#errors-legend").is_visible()
    page.check("#show-errors")
    page.wait_for_selector("#errors-layer circle.err")
    drawn = {c.get_attribute("data-label"): float(c.get_attribute("data-error"))
             for c in page.locator("#errors-layer circle.err").all()}
    assert drawn == {label: pytest.approx(p["mean_error_m"], abs=0.01) for label, p in on_ground.items()}
    assert page.locator("#errors-legend").is_visible()
    assert f"model {model['id']}" in page.text_content("#errors-legend")
    page.select_option("#floor", "1")  # the other floor's points only
    page.wait_for_function("() => document.querySelectorAll('#errors-layer circle.err').length === "
                           f"{sum(p['floor'] == 1 for p in points)}")
    assert page.errors == []
