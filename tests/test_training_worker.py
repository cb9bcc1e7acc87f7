"""The training worker outside HTTP: claiming is exclusive, dead workers' jobs come back, stop hands jobs back."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from server import repositories as repo
from server.db import Database
from server.schemas import SiteIn
from server.services.training import TrainingWorker


def queued_model(db: Database, name: str) -> int:
    with db.transaction() as s:
        site = repo.add_site(s, SiteIn(name=name))
        return repo.add_model(s, site.id, "knn", {}, False, [], True).id


def test_a_job_is_claimed_once_and_a_stale_claim_is_taken_again(clean_db):
    db = Database(clean_db)
    model_id = queued_model(db, "claims")
    now = datetime.now(UTC)
    with db.transaction() as s:
        assert repo.claim_next_model(s, now - timedelta(minutes=30)) == model_id
    with db.transaction() as s:
        assert repo.claim_next_model(s, now - timedelta(minutes=30)) is None  # still fresh
    with db.transaction() as s:
        assert repo.claim_next_model(s, now + timedelta(seconds=1)) == model_id  # its worker went quiet
    db.dispose()


def test_worker_marks_an_untrainable_job_failed_with_the_reason(clean_db):
    db = Database(clean_db)
    model_id = queued_model(db, "empty site")
    worker = TrainingWorker(clean_db)
    assert worker.run_pending() == 1
    with db.transaction() as s:
        model = repo.training_job(s, model_id)
        assert model.status == "failed" and "no fingerprints" in model.error
    worker.stop()
    db.dispose()
