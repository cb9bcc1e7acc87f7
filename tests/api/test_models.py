"""Models and locate over real HTTP: background training, metrics, activation, caching, 409/422."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.helpers.synthetic import make_site

SYNTH = make_site(nx=4, ny=3, spacing_m=4.0, floors=(0, 1), seed=2)


def wait_for(admin, site_id: int, model_id: int, timeout_s: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        model = admin.get(f"/api/v1/sites/{site_id}/models/{model_id}").json()
        if model["status"] in ("ready", "failed") or time.monotonic() > deadline:
            return model
        time.sleep(0.1)


@pytest.fixture
def site(admin) -> dict:
    floors = [{"level": 0}, {"level": 1}]
    site = admin.post("/api/v1/sites", json={"name": "Synthetic", "floors": floors,
                                             "transmitters": SYNTH.transmitters}).json()
    rows = SYNTH.survey(scans_per_rp=8, seed=1).to_rows()
    for row in rows:
        row.pop("building", None)
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows}).status_code == 201
    return site


def train(admin, site: dict, **body) -> dict:
    answer = admin.post(f"/api/v1/sites/{site['id']}/models", json=body)
    assert answer.status_code == 202, answer.text
    assert answer.json()["status"] == "queued" and answer.json()["active"] is False
    return wait_for(admin, site["id"], answer.json()["id"])


def test_first_ready_model_is_trained_in_the_background_and_activated(admin, device, site):
    model = train(admin, site, algorithm="knn", params={"k": 3})
    assert model["status"] == "ready", model
    assert model["active"] is True
    assert model["trained_on"] == len(SYNTH.rp) * 8
    metrics = model["metrics"]
    assert 0 <= metrics["mean_error_m"] < 4.0 and metrics["floor_hit_rate"] > 0.9
    assert metrics["p50_error_m"] <= metrics["p90_error_m"]

    rng = np.random.default_rng(5)
    label, x, y, floor = SYNTH.rp[4]
    answer = device.post(f"/api/v1/sites/{site['id']}/locate", json={"rss": SYNTH.scan(x, y, floor, None, rng, 1.0)})
    assert answer.status_code == 200, answer.text
    fix = answer.json()
    assert fix["floor"] == floor and fix["reference_point"] == label
    assert np.hypot(fix["x"] - x, fix["y"] - y) < 2.0
    assert fix["model_id"] == model["id"] and fix["algorithm"] == "knn"
    cov = np.array(fix["covariance"])
    assert cov.shape == (2, 2) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert fix["candidates"][0]["label"] == label


def test_second_model_stays_inactive_until_activated_and_locate_follows(admin, device, site, live_server):
    first = train(admin, site, algorithm="knn")
    second = train(admin, site, algorithm="nbc")
    assert second["status"] == "ready" and second["active"] is False
    scan = {"rss": SYNTH.scan(4.0, 4.0, 0, None, np.random.default_rng(1), 1.0)}
    assert device.post(f"/api/v1/sites/{site['id']}/locate", json=scan).json()["algorithm"] == "knn"

    activated = admin.post(f"/api/v1/sites/{site['id']}/models/{second['id']}/activate")
    assert activated.status_code == 200 and activated.json()["active"] is True
    models = {m["id"]: m for m in admin.get(f"/api/v1/sites/{site['id']}/models").json()}
    assert models[first["id"]]["active"] is False and models[second["id"]]["active"] is True
    assert device.post(f"/api/v1/sites/{site['id']}/locate", json=scan).json()["algorithm"] == "nbc"
    chosen = device.post(f"/api/v1/sites/{site['id']}/locate", json={**scan, "model_id": first["id"]})
    assert chosen.json()["model_id"] == first["id"]

    loads = live_server.app.state.positioning.cache.loads
    for _ in range(5):
        device.post(f"/api/v1/sites/{site['id']}/locate", json=scan)
    assert live_server.app.state.positioning.cache.loads == loads  # served from the cache


@pytest.mark.parametrize("algorithm", ["nbc", "knn", "svm", "kde", "tkbe", "propagation"])
def test_every_algorithm_trains_and_locates_over_http(admin, device, site, algorithm):
    model = train(admin, site, algorithm=algorithm, kinds=["wifi", "ble"])
    assert model["status"] == "ready", model["error"]
    label, x, y, floor = SYNTH.rp[7]
    scan = SYNTH.scan(x, y, floor, None, np.random.default_rng(3), 1.0)
    fix = device.post(f"/api/v1/sites/{site['id']}/locate", json={"rss": scan, "model_id": model["id"]}).json()
    assert fix["floor"] == floor
    assert np.hypot(fix["x"] - x, fix["y"] - y) < 4.0


def test_failed_training_reports_a_readable_error(admin, site):
    model = train(admin, site, algorithm="knn", kinds=["ble"], params={"k": 3})
    assert model["status"] == "ready"
    empty = admin.post("/api/v1/sites", json={"name": "No survey"}).json()
    failed = train(admin, empty, algorithm="knn")
    assert failed["status"] == "failed" and "no fingerprints" in failed["error"]
    assert failed["active"] is False


def test_locate_409_without_a_ready_model_and_422_for_unknown_transmitters(admin, device, site):
    url = f"/api/v1/sites/{site['id']}/locate"
    none_yet = device.post(url, json={"rss": {"wifi:w00": -50}})
    assert none_yet.status_code == 409
    hint = f"train one with POST /api/v1/sites/{site['id']}/models"
    assert none_yet.json() == {"detail": f"site {site['id']} has no ready model: {hint}"}
    model = train(admin, site, algorithm="knn")
    unknown = device.post(url, json={"rss": {"wifi:never-seen": -50}})
    assert unknown.status_code == 422
    assert unknown.json() == {"detail": [
        {"loc": ["body", "rss"], "field": "rss", "msg": f"no transmitter in the scan is known to model {model['id']}",
         "type": "value_error"}
    ]}
    assert device.post(url, json={"rss": {"wifi:w00": 3}}).status_code == 422
    assert device.post(url, json={"rss": {}}).status_code == 422
    assert device.post("/api/v1/sites/999/locate", json={"rss": {"wifi:w00": -50}}).status_code == 404
    assert device.post(url, json={"rss": {"wifi:w00": -50}, "model_id": 999}).status_code == 404


def test_activating_a_model_that_is_not_ready_is_409(admin, site):
    failed = train(admin, admin.post("/api/v1/sites", json={"name": "empty"}).json(), algorithm="knn")
    answer = admin.post(f"/api/v1/sites/{failed['site_id']}/models/{failed['id']}/activate")
    assert answer.status_code == 409 and "failed" in answer.json()["detail"]


@pytest.mark.parametrize(
    "body, field",
    [
        ({"algorithm": "deep-magic"}, "algorithm"),
        ({"algorithm": "knn", "params": {"k": 3, "bogus": 1}}, "params"),
        ({"algorithm": "knn", "params": {"k": 2**66}}, "params"),  # beyond what the stored JSON holds
        ({"algorithm": "knn", "params": {"k": 3, "floor_k": [1, -(2**60)]}}, "params"),
        ({"algorithm": "knn", "kinds": ["lte"]}, "kinds"),
        ({"algorithm": "knn", "kinds": []}, "kinds"),
    ],
)
def test_invalid_model_requests_are_422_and_store_nothing(admin, site, snapshot, body, field):
    before = snapshot()
    answer = admin.post(f"/api/v1/sites/{site['id']}/models", json=body)
    assert answer.status_code == 422 and answer.json()["detail"][0]["field"].startswith(field)
    assert answer.json()["detail"][0]["loc"][:2] == ["body", field]
    assert snapshot() == before


def test_model_endpoints_scope_rules(anonymous, device, site):
    for method, path in [("POST", f"/api/v1/sites/{site['id']}/models"), ("GET", f"/api/v1/sites/{site['id']}/models"),
                         ("GET", f"/api/v1/sites/{site['id']}/models/1"),
                         ("POST", f"/api/v1/sites/{site['id']}/models/1/activate")]:
        assert anonymous.request(method, path, json={"algorithm": "knn"}).status_code == 401
        assert device.request(method, path, json={"algorithm": "knn"}).status_code == 403
    assert anonymous.post(f"/api/v1/sites/{site['id']}/locate", json={"rss": {"wifi:w00": -50}}).status_code == 401


def test_a_deleted_sites_model_never_answers_for_a_new_site_that_reuses_its_ids(admin, device):
    """SQLite may hand a deleted row's id to the next row; the model cache is keyed by artifact hash."""
    answers = []
    for name, shift in (("first", 0.0), ("second", 100.0)):
        rows = SYNTH.survey(scans_per_rp=4, seed=1).to_rows()
        for row in rows:
            row.pop("building", None)
            row["x"] += shift
        site = admin.post("/api/v1/sites", json={"name": name}).json()
        admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows})
        model = train(admin, site, algorithm="knn")
        assert model["status"] == "ready"
        label, x, y, floor = SYNTH.rp[5]
        fix = device.post(f"/api/v1/sites/{site['id']}/locate",
                          json={"rss": SYNTH.scan(x, y, floor, None, np.random.default_rng(0), 1.0)}).json()
        answers.append((site["id"], model["id"], fix["x"] - shift - x))
        assert admin.delete(f"/api/v1/sites/{site['id']}").status_code == 204
    assert all(abs(dx) < 2.0 for _, _, dx in answers), answers


def test_an_artifact_that_cannot_load_is_a_409_for_locate_and_a_skipped_scan_for_a_batch(admin, device, site, clean_db):
    """A stored artifact this library refuses (an old pickle, or rewritten) never becomes a 500:
    locate answers 409 asking for a new model, a batch skips the scan with that reason."""
    import hashlib

    from sqlalchemy import create_engine, update

    from server.tables import ModelArtifact

    model = train(admin, site, algorithm="knn")
    blob = b"\x80\x04\x95not a model"  # a pickle's opening bytes; never unpickled
    engine = create_engine(clean_db)
    with engine.begin() as conn:
        conn.execute(update(ModelArtifact).where(ModelArtifact.model_id == model["id"])
                     .values(blob=blob, sha256=hashlib.sha256(blob).hexdigest()))
    engine.dispose()
    scan = SYNTH.scan(4.0, 4.0, 0, None, np.random.default_rng(1), 1.0)

    answer = device.post(f"/api/v1/sites/{site['id']}/locate", json={"rss": scan})
    assert answer.status_code == 409 and "train a new model" in answer.json()["detail"], answer.text
    sid = device.post("/api/v1/sessions", json={"site_id": site["id"], "filter": "ekf",
                                                 "initial": {"x": 4.0, "y": 4.0, "floor": 0}}).json()["id"]
    batch = device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "scans": [{"t": 1.0, "rss": scan}]})
    assert batch.status_code == 200, batch.text
    assert "train a new model" in batch.json()["skipped_scans"][0]["reason"]
