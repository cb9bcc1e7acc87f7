"""Buildings on the dashboard: a site whose two buildings share a level shows one floor per
(building, level) in the selector, and each shows only its own walls and reference points."""

from __future__ import annotations

import pytest

from tests.browser.test_dashboard import login
from tests.conftest import ADMIN_KEY

pytestmark = pytest.mark.browser


def test_two_buildings_at_the_same_level_are_two_floors(page, live_server, admin):
    site = admin.post("/api/v1/sites", json={"name": "two buildings", "floors": [
        {"level": 0, "building": 0, "name": "north hall", "walls": [[0, 0, 10, 0]]},
        {"level": 0, "building": 1, "name": "south hall", "walls": [[0, 5, 10, 5], [0, 8, 10, 8]]},
    ]})
    assert site.status_code == 201, site.text
    sid = site.json()["id"]
    tx = "wifi:aa:bb:cc:00:00:01"
    fps = [{"x": float(x), "y": 1.0, "floor": 0, "building": b, "label": f"b{b}-{x}", "rss": {tx: -50.0 - x}}
           for b, xs in ((0, (1, 3)), (1, (2, 4, 6))) for x in xs]
    answer = admin.post(f"/api/v1/sites/{sid}/surveys", json={"fingerprints": fps})
    assert answer.status_code in (200, 201), answer.text
    login(page, live_server.url, ADMIN_KEY)
    page.click(f"#sites [data-site='{sid}']")
    page.wait_for_function("document.querySelectorAll('#floor option').length === 2")
    page.wait_for_function("document.querySelectorAll('circle.rp').length === 2"
                           " && document.querySelectorAll('line.wall').length === 1")
    options = page.locator("#floor option")
    assert [options.nth(i).get_attribute("value") for i in range(options.count())] == ["0:0", "1:0"]
    assert "building 1" in options.nth(1).text_content()
    labels = lambda: sorted(c.get_attribute("data-label") for c in page.locator("circle.rp").all())  # noqa: E731
    assert labels() == ["b0-1", "b0-3"] and page.locator("line.wall").count() == 1
    page.select_option("#floor", "1:0")
    page.wait_for_function("document.querySelectorAll('circle.rp').length === 3"
                           " && document.querySelectorAll('line.wall').length === 2")
    assert labels() == ["b1-2", "b1-4", "b1-6"] and page.locator("line.wall").count() == 2
    assert page.errors == []
