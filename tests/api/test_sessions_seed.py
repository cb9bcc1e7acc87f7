"""The sessions' ``seed`` extension: the same seed and batches give the same track (a particle
filter's draws), another seed other draws; a seed out of range is a 422 that names it."""

from __future__ import annotations

import pytest

from tests.api.test_sessions import batch, open_session, site  # noqa: F401  (site: a fixture)


def _track(device, site_id: int, **extra) -> list[dict]:
    sid = open_session(device, site_id, "pf", **extra)["id"]
    for seq in range(3):
        answer = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(seq, 10.0 + 2.0 * seq, n_steps=4))
        assert answer.status_code == 200, answer.text
    return device.get(f"/api/v1/sessions/{sid}/track").json()


def test_the_same_seed_gives_the_same_track_and_another_seed_other_draws(device, site):  # noqa: F811
    first = _track(device, site, seed=7)
    assert len(first) == 1 + 12
    assert _track(device, site, seed=7) == first
    other = _track(device, site, seed=8)
    assert [(e["t"], e["source"]) for e in other] == [(e["t"], e["source"]) for e in first]
    assert [(e["x"], e["y"]) for e in other] != [(e["x"], e["y"]) for e in first]


@pytest.mark.parametrize("seed", [-1, 2**32, 1.5, "seven", [7]])
def test_a_seed_out_of_range_or_not_an_integer_is_a_422_naming_it(device, site, seed):  # noqa: F811
    answer = device.post("/api/v1/sessions", json={"site_id": site, "filter": "pf", "seed": seed})
    assert answer.status_code == 422, answer.text
    assert any(e["loc"][-1] == "seed" for e in answer.json()["detail"]), answer.text


def test_the_openapi_schema_documents_the_seed(anonymous):
    prop = anonymous.get("/openapi.json").json()["components"]["schemas"]["SessionIn"]["properties"]["seed"]
    assert "Extension" in prop["description"]
