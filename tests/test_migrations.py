"""The Alembic migrations build exactly the ORM's schema, and run down and up again."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import create_engine, inspect

from server import migrate
from server.tables import Base
from tests.conftest import scratch_database_url


def test_migrated_schema_matches_the_orm(database_url):
    engine = create_engine(database_url)
    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    engine.dispose()
    assert diff == []


def test_downgrade_to_base_and_upgrade_again(tmp_path):
    url = f"sqlite:///{tmp_path / 'm.db'}"
    migrate.upgrade(url)
    engine = create_engine(url)
    assert set(Base.metadata.tables) <= set(inspect(engine).get_table_names())
    migrate.downgrade(url, "base")
    assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
    migrate.upgrade(url)
    assert set(Base.metadata.tables) <= set(inspect(engine).get_table_names())
    engine.dispose()


def test_sqlite_connections_use_wal_and_foreign_keys(tmp_path):
    from server.db import Database

    db = Database(f"sqlite:///{tmp_path / 'p.db'}")
    with db.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    db.dispose()


def test_sqlite_site_ids_become_autoincrement_without_losing_any_sites_data(tmp_path):
    """The rebuild of ``sites`` (0006) keeps every row of its children (foreign keys off while it
    runs, so dropping the old table cascades nothing), and afterwards a deleted site's id is never
    given to a new site."""
    from server.db import Database
    from server.domain import ModelSpec, NewSite
    from server.store import models, sites

    url = f"sqlite:///{tmp_path / 'ids.db'}"
    migrate.upgrade(url, "0005_upload_requests")
    engine = create_engine(url)
    with engine.begin() as conn:
        for site_id, name in ((1, "a"), (2, "b")):
            conn.exec_driver_sql("INSERT INTO sites (id, name, settings, created_at, revision) "
                                 f"VALUES ({site_id}, '{name}', '{{}}', '2026-01-01', 'r')")
        conn.exec_driver_sql("INSERT INTO floors (site_id, level, walls) VALUES (2, 0, '[]')")
    engine.dispose()
    migrate.upgrade(url)
    db = Database(url)
    with db.engine.connect() as conn:
        assert "AUTOINCREMENT" in conn.exec_driver_sql("SELECT sql FROM sqlite_master WHERE name = 'sites'").scalar()
        assert conn.exec_driver_sql("SELECT count(*) FROM floors WHERE site_id = 2").scalar() == 1
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    with db.transaction() as s:
        model_id = models.add_model(s, 2, ModelSpec("knn", {})).id
        assert sites.delete_site(s, 2)
    with db.transaction() as s:
        assert models.get_model(s, 2, model_id) is None  # the delete still cascades
        assert sites.add_site(s, NewSite(name="c")).id == 3  # not 2 again
    db.dispose()


def test_sqlite_model_ids_become_autoincrement_without_losing_any_models_data(tmp_path):
    """The rebuild of ``models`` (0007) keeps every model, its artifact, the sessions pointing at
    it and the partial unique index (one active model per site); it cascades nothing (foreign keys
    off while it runs), and afterwards a deleted model's id is never given to a new model."""
    import pytest
    from sqlalchemy.exc import IntegrityError

    from server.db import Database
    from server.domain import ModelSpec
    from server.store import models

    url = f"sqlite:///{tmp_path / 'models.db'}"
    migrate.upgrade(url, "0006_sites_autoincrement")
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.exec_driver_sql("INSERT INTO sites (id, name, settings, created_at, revision) "
                             "VALUES (1, 'a', '{}', '2026-01-01', 'r')")
        for model_id, status, active in ((1, "ready", 1), (2, "failed", 0), (3, "queued", 0)):
            conn.exec_driver_sql(
                "INSERT INTO models (id, site_id, algorithm, params, use_heading, kinds, include_crowd, status, "
                "active, trained_on, created_at, updated_at) "
                f"VALUES ({model_id}, 1, 'knn', '{{}}', 0, '[]', 1, '{status}', {active}, 5, '2026-01-01', '2026-01-01')")
        conn.exec_driver_sql("INSERT INTO model_artifacts (model_id, sha256, blob) VALUES (1, 'abc', x'00ff')")
        conn.exec_driver_sql("INSERT INTO tracking_sessions (id, site_id, owner_key, filter, model_id, status, "
                             "last_seq, created_at, track_length) VALUES ('s1', 1, 'k', 'kf', 1, 'open', -1, "
                             "'2026-01-01', 0)")
    engine.dispose()
    before = _rows(url, "models", "model_artifacts", "tracking_sessions")

    migrate.upgrade(url, "0009_track_states")  # (0010 retrains the ready knn model: its own test below)
    assert _rows(url, "models", "model_artifacts", "tracking_sessions") == before
    db = Database(url)
    with db.engine.begin() as conn:
        assert "AUTOINCREMENT" in conn.exec_driver_sql("SELECT sql FROM sqlite_master WHERE name = 'models'").scalar()
        assert "WHERE active" in conn.exec_driver_sql(
            "SELECT sql FROM sqlite_master WHERE name = 'uq_models_one_active'").scalar()
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        with pytest.raises(IntegrityError), conn.begin_nested():  # still one active model per site
            conn.exec_driver_sql("UPDATE models SET active = 1 WHERE id = 2")
        conn.exec_driver_sql("DELETE FROM models WHERE id = 3")
    with db.transaction() as s:
        assert models.add_model(s, 1, ModelSpec("knn", {})).id == 4  # not 3 again
        conn = s.connection()
        conn.exec_driver_sql("DELETE FROM models WHERE id = 1")  # deletes still cascade and set null
        assert conn.exec_driver_sql("SELECT count(*) FROM model_artifacts").scalar() == 0
        assert conn.exec_driver_sql("SELECT model_id FROM tracking_sessions").scalar() is None
    db.dispose()

    migrate.downgrade(url, "0006_sites_autoincrement")  # and back: the rebuild keeps the rows again
    after = _rows(url, "models", "model_artifacts", "tracking_sessions")
    assert [r[0] for r in after["models"]] == [2, 4]


def _rows(url: str, *tables: str) -> dict[str, list[tuple]]:
    engine = create_engine(url)
    with engine.connect() as conn:
        rows = {t: [tuple(r) for r in conn.exec_driver_sql(f"SELECT * FROM {t} ORDER BY 1").all()] for t in tables}
    engine.dispose()
    return rows


def test_buildings_migration_keeps_v1_rows_in_building_0(tmp_path):
    """0008 puts every existing floor, reference point, fingerprint, located transmitter and track
    estimate in building 0 (a transmitter without a floor keeps no building), after which a site may
    hold the same level in two buildings but not twice in one; it downgrades and upgrades again."""
    import pytest
    from sqlalchemy.exc import IntegrityError

    url = scratch_database_url(tmp_path, "buildings")
    migrate.upgrade(url, "0007_models_autoincrement")
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.exec_driver_sql("INSERT INTO sites (id, name, settings, created_at, revision) "
                             "VALUES (1, 'a', '{}', '2026-01-01', 'r')")
        conn.exec_driver_sql("INSERT INTO floors (id, site_id, level, walls) VALUES (1, 1, 0, '[]'), (2, 1, 1, '[]')")
        conn.exec_driver_sql("INSERT INTO transmitters (site_id, tx_id, kind, floor, x, y) "
                             "VALUES (1, 'ap1', 'wifi', 1, 2.0, 3.0), (1, 'ap2', 'wifi', NULL, NULL, NULL)")
        conn.exec_driver_sql("INSERT INTO reference_points (id, site_id, floor, key, x, y) "
                             "VALUES (1, 1, 0, 'xy:1,2', 1.0, 2.0)")
        conn.exec_driver_sql("INSERT INTO fingerprints (site_id, source, reference_point_id, floor, x, y, rss, "
                             "samples, created_at) VALUES (1, 'survey', 1, 0, 1.0, 2.0, '{\"ap1\": -60}', 1, "
                             "'2026-01-01')")
        conn.exec_driver_sql("INSERT INTO tracking_sessions (id, site_id, owner_key, filter, status, last_seq, "
                             "created_at, track_length) VALUES ('s1', 1, 'k', 'kf', 'open', 0, '2026-01-01', 1)")
        conn.exec_driver_sql("INSERT INTO track_estimates (session_id, idx, x, y, floor, covariance, source) "
                             "VALUES ('s1', 0, 1.0, 2.0, 0, '[]', 'init')")
    before = _rows(url, "floors", "reference_points", "fingerprints", "transmitters", "track_estimates")

    migrate.upgrade(url)
    with engine.begin() as conn:
        for table in ("floors", "reference_points", "fingerprints", "track_estimates"):
            assert conn.exec_driver_sql(f"SELECT DISTINCT building FROM {table}").scalars().all() == [0], table
        assert conn.exec_driver_sql("SELECT tx_id, building FROM transmitters ORDER BY tx_id").all() == [
            ("ap1", 0), ("ap2", None)]
        assert conn.exec_driver_sql("SELECT walkable FROM floors").scalars().all() == [None, None]
        conn.exec_driver_sql("INSERT INTO floors (id, site_id, building, level, walls) VALUES (3, 1, 1, 0, '[]')")
        conn.exec_driver_sql("INSERT INTO reference_points (id, site_id, building, floor, key, x, y) "
                             "VALUES (2, 1, 1, 0, 'xy:1,2', 1.0, 2.0)")
        with pytest.raises(IntegrityError), conn.begin_nested():
            conn.exec_driver_sql("INSERT INTO floors (id, site_id, building, level, walls) VALUES (4, 1, 1, 0, '[]')")
        with pytest.raises(IntegrityError), conn.begin_nested():
            conn.exec_driver_sql("INSERT INTO reference_points (id, site_id, building, floor, key, x, y) "
                                 "VALUES (3, 1, 0, 0, 'xy:1,2', 5.0, 5.0)")
        names = {ix["name"] for ix in inspect(conn).get_indexes("tracking_sessions")}
        assert "ix_tracking_sessions_created_id" in names
        conn.exec_driver_sql("DELETE FROM reference_points WHERE building = 1")
        conn.exec_driver_sql("DELETE FROM floors WHERE building = 1")
    engine.dispose()

    migrate.downgrade(url, "0007_models_autoincrement")
    assert _rows(url, "floors", "reference_points", "fingerprints", "transmitters", "track_estimates") == before
    migrate.upgrade(url)
    engine = create_engine(url)
    with engine.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []
    engine.dispose()


def _previous_knn_artifact() -> bytes:
    """An artifact as the knn before 0010 left it: its state holds the ``dist_`` of its own search."""
    import numpy as np

    from server.estimation.fingerprint import FingerprintSet, make_model, to_bytes

    model = make_model("knn").fit(FingerprintSet.from_rows(
        [{"x": float(i), "y": 0.0, "floor": 0, "rss": {"wifi:a": -40.0 - 5 * i, "wifi:b": -70.0 + 5 * i}} for i in range(4)]))
    model.dist_ = np.zeros(1)
    return to_bytes(model)


def test_knn_models_are_trained_again_with_the_rebuilt_knn(tmp_path):
    """0010 sends every ready knn model back to the queue without its artifact (which the rebuilt
    knn refuses); the worker's retrain makes each ready again, active as it was, and loadable.
    Other models, and knn models that were not ready, are left as they were."""
    import math

    import pytest
    from sqlalchemy import text

    from server.db import Database
    from server.domain import FingerprintRecord, ModelSpec, NewSite
    from server.estimation.fingerprint import ArtifactError, KNNModel, from_bytes
    from server.services.training import TrainingWorker
    from server.store import models, sites, surveys

    url = scratch_database_url(tmp_path, "knn_retrain")
    migrate.upgrade(url, "0009_track_states")
    aps = {"wifi:a": (0.0, 0.0), "wifi:b": (12.0, 0.0), "wifi:c": (0.0, 9.0), "wifi:d": (12.0, 9.0)}
    survey = [FingerprintRecord(float(x), float(y), 0, {t: -40.0 - 20.0 * math.log10(1.0 + math.hypot(x - ax, y - ay)) - d
                                                        for t, (ax, ay) in aps.items()}, device=f"phone{d}")
              for x in range(0, 13, 3) for y in range(0, 10, 3) for d in range(3)]
    old_blob = _previous_knn_artifact()
    with pytest.raises(ArtifactError, match="previous knn"):
        from_bytes(old_blob)
    db = Database(url)
    with db.transaction() as s:
        site = sites.add_site(s, NewSite(name="a")).id
        surveys.add_survey(s, site, survey, None, 0)
        ids = [models.add_model(s, site, ModelSpec(algorithm, {})).id for algorithm in ("knn", "knn", "wknn", "knn")]
    with db.engine.begin() as conn:
        for model_id, status, active in zip(ids, ("ready", "ready", "ready", "failed"), (True, False, False, False),
                                            strict=True):
            conn.execute(text("UPDATE models SET status = :status, active = :active WHERE id = :id"),
                         {"status": status, "active": active, "id": model_id})
        for model_id in ids[:3]:
            conn.execute(text("INSERT INTO model_artifacts (model_id, sha256, blob) VALUES (:id, :sha, :blob)"),
                         {"id": model_id, "sha": f"sha{model_id}", "blob": old_blob})
    before = _rows(url, "models", "model_artifacts")

    migrate.upgrade(url)
    after = {r[0]: r for r in _rows(url, "models")["models"]}
    with db.transaction() as s:
        info = {i: models.training_job(s, i) for i in ids}
        assert [info[i].status for i in ids] == ["queued", "queued", "ready", "failed"]
        assert [info[i].active for i in ids] == [True, False, False, False]
        assert [info[i].activate for i in ids[:2]] == ["always", "never"]
        assert models.model_artifact(s, ids[0]) is None and models.model_artifact(s, ids[1]) is None
    assert [after[i] for i in ids[2:]] == [r for r in before["models"] if r[0] in ids[2:]]
    assert _rows(url, "model_artifacts")["model_artifacts"] == [r for r in before["model_artifacts"] if r[0] == ids[2]]

    worker = TrainingWorker(url)
    assert worker.run_pending() == 2
    worker.stop()
    with db.transaction() as s:
        retrained = [models.training_job(s, i) for i in ids[:2]]
        assert [(m.status, m.active) for m in retrained] == [("ready", True), ("ready", False)]
        assert models.active_model(s, site).id == ids[0]
        model = from_bytes(models.model_artifact(s, ids[0]).blob)
    assert isinstance(model, KNNModel)
    fix = model.locate(dict(survey[0].rss))
    assert math.hypot(fix.x - survey[0].x, fix.y - survey[0].y) < 3.0
    db.dispose()
