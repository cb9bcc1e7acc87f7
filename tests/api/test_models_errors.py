"""GET …/models/{id}/errors: each held-out reference point's mean error, from training."""

from __future__ import annotations

import numpy as np

from tests.api.test_models import SYNTH, site, train, wait_for  # noqa: F401  (the site fixture)


def test_held_out_errors_are_the_models_held_out_scans_per_reference_point(admin, device, site):  # noqa: F811
    model = train(admin, site, algorithm="knn")
    answer = admin.get(f"/api/v1/sites/{site['id']}/models/{model['id']}/errors")
    assert answer.status_code == 200, answer.text
    points = answer.json()
    assert points and all(set(p) == {"building", "floor", "x", "y", "label", "n", "mean_error_m"} for p in points)
    surveyed = {(label, x, y, f) for label, x, y, f in SYNTH.rp}
    assert all((p["label"], p["x"], p["y"], p["floor"]) in surveyed and p["n"] >= 1 and p["mean_error_m"] >= 0
               for p in points)
    # together they are the held-out sample the model's metrics come from
    n = np.array([p["n"] for p in points])
    assert n.sum() == model["metrics"]["validated_on"]
    mean = float(np.sum(n * np.array([p["mean_error_m"] for p in points])) / n.sum())
    assert abs(mean - model["metrics"]["mean_error_m"]) < 0.01

    assert device.get(f"/api/v1/sites/{site['id']}/models/{model['id']}/errors").status_code == 403
    assert admin.get(f"/api/v1/sites/{site['id']}/models/{model['id'] + 99}/errors").status_code == 404


def test_a_model_that_is_not_ready_has_no_errors_yet(admin):
    empty = admin.post("/api/v1/sites", json={"name": "no survey"}).json()
    queued = admin.post(f"/api/v1/sites/{empty['id']}/models", json={"algorithm": "knn"}).json()
    failed = wait_for(admin, empty["id"], queued["id"])
    assert failed["status"] == "failed"
    answer = admin.get(f"/api/v1/sites/{empty['id']}/models/{queued['id']}/errors")
    assert answer.status_code == 409 and "failed" in answer.text
