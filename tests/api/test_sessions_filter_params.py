"""The sessions' ``filter_params`` extension: numbers that override a tracker's defaults, kept
with the session (echoed, applied to every batch); an unknown name, a value out of range, a
fraction where a count is meant or parameters a tracker refuses together are a 422 naming them,
and nothing is stored."""

from __future__ import annotations

import json

import pytest

from tests.api.test_sessions import batch, open_session, site  # noqa: F401  (site: a fixture)


def _track(device, site_id: int, filter: str = "pf", **extra) -> list[dict]:
    sid = open_session(device, site_id, filter, seed=7, **extra)["id"]
    for seq in range(3):
        answer = device.post(f"/api/v1/sessions/{sid}/batches", json=batch(seq, 10.0 + 2.0 * seq, n_steps=4))
        assert answer.status_code == 200, answer.text
    return device.get(f"/api/v1/sessions/{sid}/track").json()


def test_params_are_kept_echoed_and_change_the_track(device, site):  # noqa: F811
    params = {"n_particles": 300, "q": 0.2}
    opened = open_session(device, site, "pf", filter_params=params)
    assert opened["filter_params"] == params and isinstance(opened["filter_params"]["n_particles"], int)
    assert device.get(f"/api/v1/sessions/{opened['id']}").json()["filter_params"] == params
    assert "filter_params" not in open_session(device, site, "pf")  # the defaults
    listed = device.get("/api/v1/sessions").json()
    assert listed and all("filter_params" not in s for s in listed)  # a list reads no tracker state
    # the same seed and batches: the same parameters give the same track, others another one
    tuned = _track(device, site, filter_params=params)
    assert _track(device, site, filter_params=params) == tuned
    default = _track(device, site)
    assert [(e["t"], e["source"]) for e in default] == [(e["t"], e["source"]) for e in tuned]
    assert [(e["x"], e["y"]) for e in default] != [(e["x"], e["y"]) for e in tuned]


def test_a_kalman_filter_takes_its_own_parameters(device, site):  # noqa: F811
    # kf with a huge process noise follows its steps as the default does (no fixes here) but its
    # covariance grows faster
    wide = _track(device, site, "kf", filter_params={"q": 50})
    plain = _track(device, site, "kf")
    assert wide[-1]["covariance"][0][0] > 10 * plain[-1]["covariance"][0][0]


BAD = [
    ({"nope": 1}, "filter_params.nope", "not a parameter of pf"),
    ({"r": 4.0}, "filter_params.r", "not a parameter of pf"),  # kf's, not the PF's
    ({"n_particles": 250.5}, "filter_params.n_particles", "whole number"),
    ({"n_particles": 1_000_000}, "filter_params.n_particles", "between 2 and 10000"),
    ({"q": -0.1}, "filter_params.q", "between 0 and 100"),
    ({"q": 10**400}, "filter_params.q", "between 0 and 100"),  # an int no float holds
    ({"n_particles": 100, "min_particles": 500}, "filter_params", "min_particles"),
]


@pytest.mark.parametrize("params, field, words", BAD)
def test_bad_params_are_a_422_naming_them_and_store_nothing(device, site, snapshot, params, field, words):  # noqa: F811
    before = snapshot()
    answer = device.post("/api/v1/sessions", json={"site_id": site, "filter": "pf", "filter_params": params})
    assert answer.status_code == 422, answer.text
    detail = answer.json()["detail"]
    assert any(d.get("field") == field and words in d["msg"] for d in detail), detail
    assert snapshot() == before


@pytest.mark.parametrize("params", [{"q": "0.1"}, {"q": True}, {"q": None}, {"q": [1]}, [1, 2], "q=1",
                                    {f"p{i}": 1 for i in range(40)}, {"q" * 100: 1}])
def test_params_that_are_not_a_small_map_of_numbers_are_a_422(device, site, snapshot, params):  # noqa: F811
    before = snapshot()
    answer = device.post("/api/v1/sessions", json={"site_id": site, "filter": "pf", "filter_params": params})
    assert answer.status_code == 422, answer.text
    assert any("filter_params" in json.dumps(d["loc"]) for d in answer.json()["detail"]), answer.text
    assert snapshot() == before


def test_nan_is_refused(device, site):  # noqa: F811
    body = '{"site_id": ' + str(site) + ', "filter": "pf", "filter_params": {"q": NaN}}'
    answer = device.post("/api/v1/sessions", content=body, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422, answer.text


def test_the_openapi_schema_lists_each_filters_parameters(anonymous):
    prop = anonymous.get("/openapi.json").json()["components"]["schemas"]["SessionIn"]["properties"]["filter_params"]
    assert "Extension" in prop["description"] and "`pf`: n_particles (particles, 2–10000, default 1000)" in prop["description"]
