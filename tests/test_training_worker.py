"""The training worker outside HTTP: claiming is exclusive, dead workers' jobs come back, stop hands jobs back."""

from __future__ import annotations

import time
from datetime import UTC, datetime, timedelta

import numpy as np

from server.db import Database
from server.domain import FingerprintRecord, ModelSpec, NewSite
from server.services import training
from server.services.training import TrainingWorker, run_training_job
from server.store import models, sites, surveys


def queued_model(db: Database, name: str, fingerprints: int = 0) -> int:
    """A knn model queued on a new site with a synthetic survey of ``fingerprints`` rows (30 APs,
    log-distance RSS; none: the job fails at once)."""
    rng = np.random.default_rng(0)
    aps = rng.uniform(0, 100, (30, 2))
    survey = []
    for _ in range(fingerprints):
        xy = rng.uniform(0, 100, 2)
        d = np.maximum(np.hypot(*(aps - xy).T), 1.0)
        rss = -40.0 - 25.0 * np.log10(d) + rng.normal(0, 3, len(d))
        survey.append(FingerprintRecord(float(xy[0]), float(xy[1]), 0,
                                        {f"wifi:ap{j}": float(round(rss[j])) for j in np.flatnonzero(d < 60)}))
    with db.transaction() as s:
        site = sites.add_site(s, NewSite(name=name))
        if survey:
            surveys.add_survey(s, site.id, survey, None, 0)
        return models.add_model(s, site.id, ModelSpec("knn", {})).id


def test_a_job_is_claimed_once_and_a_stale_claim_is_taken_again(own_db):
    db = Database(own_db)
    model_id = queued_model(db, "claims")
    now = datetime.now(UTC)
    with db.transaction() as s:
        assert models.claim_next_model(s, now - timedelta(minutes=30)) == model_id
    with db.transaction() as s:
        assert models.claim_next_model(s, now - timedelta(minutes=30)) is None  # still fresh
    with db.transaction() as s:
        assert models.claim_next_model(s, now + timedelta(seconds=1)) == model_id  # its worker went quiet
    db.dispose()


def test_worker_marks_an_untrainable_job_failed_with_the_reason(own_db):
    db = Database(own_db)
    model_id = queued_model(db, "empty site")
    worker = TrainingWorker(own_db)
    assert worker.run_pending() == 1
    with db.transaction() as s:
        model = models.training_job(s, model_id)
        assert model.status == "failed" and "no fingerprints" in model.error
    worker.stop()
    db.dispose()


def test_a_survey_grid_that_cannot_be_measured_leaves_the_model_ready_without_it(own_db, monkeypatch, caplog):
    """The survey's grid is the trackers' heading reference, not part of the model: an error while
    measuring it stores the model without a grid (and says so in the log) instead of failing the job."""
    db = Database(own_db)
    model_id = queued_model(db, "grid fails", fingerprints=120)
    with db.transaction() as s:
        assert models.claim_next_model(s, datetime.now(UTC) - timedelta(minutes=30)) == model_id

    def broken(*args, **kwargs):
        raise FloatingPointError("degenerate floor")

    monkeypatch.setattr(training, "survey_grids", broken)
    assert run_training_job(own_db, model_id) == "ready"
    with db.transaction() as s:
        model = models.training_job(s, model_id)
        assert model is not None and model.status == "ready" and model.error is None
        assert model.metrics is not None and model.metrics["survey_grid"] == []
        assert models.survey_grids(s, model_id) == {}
    assert "survey's grid could not be measured" in caplog.text and "FloatingPointError" in caplog.text
    db.dispose()


def test_a_live_workers_job_is_never_claimed_again_however_long_it_trains(own_db):
    """The worker renews its claim while the child trains (a heartbeat every sixth of the stale
    time), so another worker never starts a second copy of a job whose worker is alive. The job
    trains on 3,000 fingerprints (≈ 1–1.5 s with the child's start) so that it is watched training
    for longer than the stale time (an empty site's job once failed within it on a warm machine)."""
    db = Database(own_db)
    model_id = queued_model(db, "heartbeat", fingerprints=3000)
    worker = TrainingWorker(own_db, poll_s=0.05, stale_after_s=0.6).start()
    checks_while_training = 0
    deadline = time.monotonic() + 60
    try:
        while time.monotonic() < deadline:
            with db.transaction() as s:
                status = models.training_job(s, model_id).status
            if status in ("ready", "failed"):
                break
            if status == "training":
                with db.transaction(rollback_only=True) as s:
                    assert models.claim_next_model(s, datetime.now(UTC) - timedelta(seconds=0.6)) is None
                checks_while_training += 1
            time.sleep(0.1)
    finally:
        worker.stop()
    # watched training for ≥ 0.7 s (checks every 0.1 s and more): past the stale time of 0.6 s
    assert status == "ready" and checks_while_training >= 7, (status, checks_while_training)
    db.dispose()
