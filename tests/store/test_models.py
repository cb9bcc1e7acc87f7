"""Models: jobs and their claims, training outcomes, artifacts, the one active model per site."""

from __future__ import annotations

import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import update
from sqlalchemy.exc import IntegrityError

from server.db import Database
from server.domain import Artifact, ModelSpec, NewSite, ServingCandidate, ServingModel
from server.store import models, sites
from server.tables import Model

KNN = ModelSpec("knn", {"k": 3}, use_heading=True, kinds=("ble", "wifi"), include_crowd=False)
STALE = timedelta(minutes=30)


@pytest.fixture
def db(own_db: str) -> Iterator[Database]:
    """A database of its own: the shared live server's training worker would claim these jobs."""
    database = Database(own_db)
    yield database
    database.dispose()


def ready_model(db, site_id: int, blob: bytes = b"model", sha256: str = "f" * 64) -> int:
    with db.transaction() as s:
        model_id = models.add_model(s, site_id, KNN).id  # one transaction: no live server's worker claims it first
        s.execute(update(Model).where(Model.id == model_id).values(status="training", claimed_at=datetime.now(UTC)))
        assert models.finish_training(s, model_id, blob, sha256, trained_on=12, metrics={"mean_error_m": 1.5})
    return model_id


def revision(db, site_id: int) -> str:
    with db.transaction() as s:
        site = sites.get_site(s, site_id)
        assert site is not None
        return site.revision


def test_a_queued_model_round_trips(db, site_id):
    with db.transaction() as s:
        added = models.add_model(s, site_id, KNN)
    assert added.spec == KNN and added.status == "queued" and not added.active and added.trained_on == 0
    with db.transaction() as s:
        assert models.get_model(s, site_id, added.id) == added
        assert models.get_model(s, site_id + 1000, added.id) is None  # not a model of that site
        assert models.list_models(s, site_id) == [added]
        assert models.training_job(s, added.id) == added
        assert models.model_site(s, added.id) == site_id and models.model_site(s, added.id + 1000) is None


def test_jobs_are_claimed_oldest_first_once_and_again_when_their_worker_went_quiet(db, site_id):
    with db.transaction() as s:
        first, second = models.add_model(s, site_id, KNN).id, models.add_model(s, site_id, KNN).id
    now = datetime.now(UTC)
    with db.transaction() as s:
        assert models.claim_next_model(s, now - STALE) == first
    with db.transaction() as s:
        assert models.claim_next_model(s, now - STALE) == second
    with db.transaction() as s:
        assert models.claim_next_model(s, now - STALE) is None
        job = models.training_job(s, first)
        assert job is not None and job.status == "training"
    with db.transaction() as s:
        assert models.claim_next_model(s, datetime.now(UTC) + timedelta(seconds=1)) == first  # stale claim


def test_a_requeued_job_can_be_claimed_again_and_a_failure_keeps_its_reason(db, site_id):
    with db.transaction() as s:
        model_id = models.add_model(s, site_id, KNN).id
        models.requeue_model(s, model_id)  # only a job in training goes back
        assert models.claim_next_model(s, datetime.now(UTC) - STALE) == model_id
        models.requeue_model(s, model_id)
        assert models.claim_next_model(s, datetime.now(UTC) - STALE) == model_id
        models.fail_training(s, model_id, "x" * 5000)
    with db.transaction() as s:
        failed = models.get_model(s, site_id, model_id)
        assert failed is not None and failed.status == "failed" and failed.error == "x" * 2000
        assert models.claim_next_model(s, datetime.now(UTC) - STALE) is None


def test_status_changes_are_compare_and_set_from_training(db, site_id):
    """Only a job in training becomes ready, failed or queued again: a ready model that a late
    failure report (its process ended by a signal just after storing it) reaches stays ready."""
    with db.transaction() as s:
        queued = models.add_model(s, site_id, KNN).id
        assert not models.finish_training(s, queued, b"m", "a" * 64, 1, None)  # never claimed
        assert not models.fail_training(s, queued, "boom") and not models.heartbeat(s, queued)
    model_id = ready_model(db, site_id)
    with db.transaction() as s:
        assert not models.fail_training(s, model_id, "the training process died (exit code -15)")
        assert not models.requeue_model(s, model_id)
        assert not models.finish_training(s, model_id, b"other", "b" * 64, 1, None)  # a second copy's outcome
        assert not models.heartbeat(s, model_id)
    with db.transaction() as s:
        info = models.get_model(s, site_id, model_id)
        assert info is not None and info.status == "ready" and info.error is None
        assert models.model_artifact(s, model_id) == Artifact(model_id, "f" * 64, b"model")


def test_a_heartbeat_keeps_a_live_job_from_being_claimed_again(db, site_id):
    with db.transaction() as s:
        model_id = models.add_model(s, site_id, KNN).id
        assert models.claim_next_model(s, datetime.now(UTC)) == model_id
    stale = timedelta(seconds=0.3)
    for _ in range(3):
        time.sleep(0.2)
        with db.transaction() as s:
            assert models.heartbeat(s, model_id)
        with db.transaction() as s:
            assert models.claim_next_model(s, datetime.now(UTC) - stale) is None  # its worker lives
    time.sleep(0.4)  # no heartbeat: the worker died
    with db.transaction() as s:
        assert models.claim_next_model(s, datetime.now(UTC) - stale) == model_id


def test_a_trained_model_serves_with_its_artifact(db, site_id):
    with db.transaction() as s:
        assert models.serving_model(s.connection(), site_id, None) is None
        queued = models.add_model(s, site_id, KNN).id
    with db.read() as conn:
        assert models.serving_model(conn, site_id, queued) == ServingCandidate(queued, "knn", "queued", None)
    model_id = ready_model(db, site_id, b"\x00blob", "a" * 64)
    with db.transaction() as s:
        info = models.get_model(s, site_id, model_id)
        assert info is not None and info.status == "ready" and info.trained_on == 12 and info.metrics == {"mean_error_m": 1.5}
        chosen = models.serving_model(s.connection(), site_id, model_id)
        assert chosen is not None and chosen.ready() == ServingModel(model_id, "knn", "a" * 64)
        assert models.serving_model(s.connection(), site_id, None) is None  # trained, not yet active
        assert models.serving_model(s.connection(), site_id + 1000, model_id) is None
        assert models.model_artifact(s, model_id) == Artifact(model_id, "a" * 64, b"\x00blob")
        assert models.model_artifact(s, queued) is None


def test_activation_keeps_one_active_model_per_site_and_renews_the_revision(db, site_id):
    first, second = ready_model(db, site_id), ready_model(db, site_id)
    with db.transaction() as s:
        other_site = sites.add_site(s, NewSite(name="other")).id
    other = ready_model(db, other_site)
    before = revision(db, site_id)
    with db.transaction() as s:
        assert not models.has_active_model(s, site_id)
        models.activate_model(s, site_id, first)
        models.activate_model(s, other_site, other)
    assert revision(db, site_id) != before
    with db.transaction() as s:
        models.activate_model(s, site_id, second)
    with db.transaction() as s:
        assert models.has_active_model(s, site_id)
        assert [m.active for m in models.list_models(s, site_id)] == [False, True]
        active = models.serving_model(s.connection(), site_id, None)
        assert active is not None and active.model_id == second
        assert models.serving_model(s.connection(), other_site, None) == ServingCandidate(other, "knn", "ready", "f" * 64)
    with pytest.raises(IntegrityError), db.transaction() as s:  # the database itself allows one
        s.execute(update(Model).where(Model.id == first).values(active=True))
