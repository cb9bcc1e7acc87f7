"""Tracking sessions with a real trained fingerprint model (synthetic site, knn):
cold start from the first scan, fixes pulling the track onto the walk, fkf's search box,
crowd fingerprints from confident estimates; a crowd-trained model answers outside the search circle."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sqlalchemy import create_engine, text

from tests.api.test_models import wait_for
from tests.helpers.synthetic import make_site

SYNTH = make_site(nx=4, ny=3, spacing_m=4.0, floors=(0, 1), seed=2)


@pytest.fixture
def trained(admin) -> dict:
    site = admin.post("/api/v1/sites", json={"name": "Synthetic", "floors": [{"level": 0}, {"level": 1}],
                                             "transmitters": SYNTH.transmitters}).json()
    rows = SYNTH.survey(scans_per_rp=8, seed=1).to_rows()
    for row in rows:
        row.pop("building", None)
    assert admin.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows}).status_code == 201
    answer = admin.post(f"/api/v1/sites/{site['id']}/models", json={"algorithm": "knn", "params": {"k": 3}})
    model = wait_for(admin, site["id"], answer.json()["id"])
    assert model["status"] == "ready", model
    return {"site": site["id"], "model": model["id"]}


def walk_batches(n_batches: int, start=(0.0, 0.0), heading=90.0, floor=0, seed=0):
    """A straight walk along +x at 1 step (0.7 m) per 0.5 s, one scan per second."""
    rng = np.random.default_rng(seed)
    x, y = start
    t, out, truth = 0.0, [], []
    for seq in range(n_batches):
        steps, scans = [], []
        for _ in range(2):
            t += 0.5
            x += 0.7 * math.sin(math.radians(heading))
            y += 0.7 * math.cos(math.radians(heading))
            steps.append({"t": t, "length_m": 0.7, "heading_deg": heading})
        scans.append({"t": t + 0.01, "rss": SYNTH.scan(x, y, floor, None, rng, 1.0)})
        truth.append((x, y))
        out.append({"seq": seq, "steps": steps, "scans": scans})
    return out, truth


@pytest.mark.parametrize("name", ["skpf", "ekf", "fkf"])
def test_cold_start_and_tracking_with_a_trained_model(device, trained, name):
    sid = device.post("/api/v1/sessions", json={"site_id": trained["site"], "filter": name}).json()["id"]
    batches, truth = walk_batches(12, start=(0.5, 4.0))
    errors = []
    for b, (x, y) in zip(batches, truth, strict=True):
        r = device.post(f"/api/v1/sessions/{sid}/batches", json=b)
        assert r.status_code == 200, r.text
        r = r.json()
        assert r["skipped_scans"] == []
        errors.append(math.hypot(r["estimate"]["x"] - x, r["estimate"]["y"] - y))
        assert r["estimate"]["floor"] == 0
    first = device.get(f"/api/v1/sessions/{sid}/track").json()[0]
    assert first["source"] == "scan"  # cold start: the first scan's fused fix
    assert errors[0] < 4.0 and np.mean(errors) < 3.0, errors


def test_a_pinned_model_is_used_and_reported(device, trained):
    s = device.post("/api/v1/sessions", json={"site_id": trained["site"], "filter": "kf", "model_id": trained["model"]})
    assert s.status_code == 201 and s.json()["model_id"] == trained["model"]


def test_crowdsourcing_with_a_trained_model(admin, device, trained, clean_db):
    admin.patch(f"/api/v1/sites/{trained['site']}", json={"settings": {"crowdsourcing": True}})
    sid = device.post("/api/v1/sessions", json={"site_id": trained["site"], "filter": "kf",
                                                "initial": {"x": 4.0, "y": 4.0, "floor": 0}}).json()["id"]
    rng = np.random.default_rng(3)
    for seq in range(6):  # standing still at a reference point
        scan = {"t": float(seq), "rss": SYNTH.scan(4.0, 4.0, 0, None, rng, 1.0)}
        assert device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": seq, "scans": [scan]}).status_code == 200
    engine = create_engine(clean_db)
    with engine.connect() as conn:
        rows = conn.execute(text("SELECT x, y, samples FROM fingerprints WHERE source = 'crowd'")).all()
    engine.dispose()
    assert len(rows) >= 1 and sum(r[2] for r in rows) >= 3
    assert all(math.hypot(r[0] - 4.0, r[1] - 4.0) < 2.0 for r in rows)


def test_a_crowd_trained_model_answers_anywhere(admin, device, trained, clean_db, live_server):
    """A session's search circle restricts a survey-only model; a model trained on crowd fingerprints
    answers anywhere: its positions are where earlier sessions believed they were, and the circle would
    let that map confirm the sessions' shared error (docs/tracking-design.md, "A defect the circle
    brought")."""
    positioning = live_server.app.state.positioning
    scan = SYNTH.scan(0.0, 0.0, 0, None, np.random.default_rng(5), 1.0)
    far = {"near": (12.0, 8.0), "radius_m": 3.0}  # the grid's far corner; the walker stands at (0, 0)

    def answer(model_id, **near):
        f = positioning.locate(trained["site"], scan, model_id=model_id, **near).fix
        return np.array([f.x, f.y])

    survey_free, survey_near = answer(trained["model"]), answer(trained["model"], **far)
    assert np.hypot(*survey_free) < 3.0 and np.hypot(*(survey_near - far["near"])) <= far["radius_m"]

    admin.patch(f"/api/v1/sites/{trained['site']}", json={"settings": {"crowdsourcing": True}})
    sid = device.post("/api/v1/sessions", json={"site_id": trained["site"], "filter": "kf",
                                                "initial": {"x": 4.0, "y": 4.0, "floor": 0}}).json()["id"]
    rng = np.random.default_rng(3)
    for seq in range(6):  # standing still at a reference point: crowd fingerprints there
        standing = {"t": float(seq), "rss": SYNTH.scan(4.0, 4.0, 0, None, rng, 1.0)}
        assert device.post(f"/api/v1/sessions/{sid}/batches", json={"seq": seq, "scans": [standing]}).status_code == 200
    engine = create_engine(clean_db)
    with engine.connect() as conn:
        counts = dict(conn.execute(text("SELECT source, count(*) FROM fingerprints GROUP BY source")).all())
    engine.dispose()
    assert counts["crowd"] >= 1
    crowd = wait_for(admin, trained["site"], admin.post(f"/api/v1/sites/{trained['site']}/models",
                                                        json={"algorithm": "knn", "params": {"k": 3}}).json()["id"])
    assert crowd["status"] == "ready", crowd
    serving = positioning.serving_model(trained["site"], crowd["id"])
    model = positioning.cache.get(serving.model_id, serving.sha256)
    assert model.crowd_share_ == pytest.approx(counts["crowd"] / (counts["crowd"] + counts["survey"]))
    assert crowd["metrics"]["crowd_share"] == pytest.approx(model.crowd_share_)  # what the admin sees
    assert admin.get(f"/api/v1/sites/{trained['site']}/models/{trained['model']}").json()["metrics"].get(
        "crowd_share") in (None, 0.0)  # the survey-only model (stored before crowd data existed)

    crowd_free, crowd_near = answer(crowd["id"]), answer(crowd["id"], **far)
    assert np.allclose(crowd_near, crowd_free) and np.hypot(*crowd_free) < 3.0
