"""The training worker outside HTTP: claiming is exclusive, dead workers' jobs come back, stop hands jobs back."""

from __future__ import annotations

import time
from datetime import UTC, datetime, timedelta

from server.db import Database
from server.domain import ModelSpec, NewSite
from server.services.training import TrainingWorker
from server.store import models, sites


def queued_model(db: Database, name: str) -> int:
    with db.transaction() as s:
        site = sites.add_site(s, NewSite(name=name))
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


def test_a_live_workers_job_is_never_claimed_again_however_long_it_trains(own_db):
    """The worker renews its claim while the child trains (a heartbeat every sixth of the stale
    time), so another worker never starts a second copy of a job whose worker is alive."""
    db = Database(own_db)
    model_id = queued_model(db, "heartbeat")
    worker = TrainingWorker(own_db, poll_s=0.05, stale_after_s=0.6).start()
    checks_while_training = 0
    deadline = time.monotonic() + 60
    try:
        while time.monotonic() < deadline:
            with db.transaction() as s:
                status = models.training_job(s, model_id).status
            if status == "failed":
                break
            if status == "training":
                with db.transaction(rollback_only=True) as s:
                    assert models.claim_next_model(s, datetime.now(UTC) - timedelta(seconds=0.6)) is None
                checks_while_training += 1
            time.sleep(0.1)
    finally:
        worker.stop()
    assert status == "failed" and checks_while_training >= 5  # the spawned child took seconds, past the stale time
    db.dispose()
