"""The training worker outside HTTP: claiming is exclusive, dead workers' jobs come back, stop hands jobs back."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from server.db import Database
from server.domain import ModelSpec, NewSite
from server.services.training import TrainingWorker
from server.store import models, sites


def queued_model(db: Database, name: str) -> int:
    with db.transaction() as s:
        site = sites.add_site(s, NewSite(name=name))
        return models.add_model(s, site.id, ModelSpec("knn", {})).id


def test_a_job_is_claimed_once_and_a_stale_claim_is_taken_again(clean_db):
    db = Database(clean_db)
    model_id = queued_model(db, "claims")
    now = datetime.now(UTC)
    with db.transaction() as s:
        assert models.claim_next_model(s, now - timedelta(minutes=30)) == model_id
    with db.transaction() as s:
        assert models.claim_next_model(s, now - timedelta(minutes=30)) is None  # still fresh
    with db.transaction() as s:
        assert models.claim_next_model(s, now + timedelta(seconds=1)) == model_id  # its worker went quiet
    db.dispose()


def test_worker_marks_an_untrainable_job_failed_with_the_reason(clean_db):
    db = Database(clean_db)
    model_id = queued_model(db, "empty site")
    worker = TrainingWorker(clean_db)
    assert worker.run_pending() == 1
    with db.transaction() as s:
        model = models.training_job(s, model_id)
        assert model.status == "failed" and "no fingerprints" in model.error
    worker.stop()
    db.dispose()
