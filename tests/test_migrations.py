"""The Alembic migrations build exactly the ORM's schema, and run down and up again."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import create_engine, inspect

from server import migrate
from server.tables import Base


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
