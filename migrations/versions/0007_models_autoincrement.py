"""SQLite: model ids are never reused (AUTOINCREMENT), so a client holding a deleted model's id
cannot read or activate another model

SQLite rebuilds the table for this. ``migrations/env.py`` turns foreign keys off around SQLite
migrations: with them on, dropping the old table would cascade-delete every model's artifact and
set every session's ``model_id`` to NULL. The rebuild keeps every id and the partial unique index
(at most one active model per site), and checks both and the foreign keys before it commits.
PostgreSQL sequences never reuse ids: nothing to do there.

Revision ID: 0007_models_autoincrement
Revises: 0006_sites_autoincrement
Create Date: 2026-12-01 13:00:00
"""
from alembic import op

revision = '0007_models_autoincrement'
down_revision = '0006_sites_autoincrement'
branch_labels = None
depends_on = None


def _indexes(bind) -> dict[str, str]:
    return dict(bind.exec_driver_sql(
        "SELECT name, sql FROM sqlite_master WHERE type = 'index' AND tbl_name = 'models' AND sql IS NOT NULL").all())


def _rebuild_models(autoincrement: bool) -> None:
    bind = op.get_bind()
    if bind.dialect.name != "sqlite":
        return
    if bind.exec_driver_sql("PRAGMA foreign_keys").scalar():
        raise RuntimeError("rebuilding models with foreign keys on would cascade-delete every model's artifact")
    indexes = _indexes(bind)
    counts = {t: bind.exec_driver_sql(f"SELECT count(*) FROM {t}").scalar()
              for t in ("models", "model_artifacts", "tracking_sessions")}
    linked = bind.exec_driver_sql("SELECT count(*) FROM tracking_sessions WHERE model_id IS NOT NULL").scalar()
    with op.batch_alter_table('models', recreate='always', table_kwargs={'sqlite_autoincrement': autoincrement}):
        pass
    if _indexes(bind) != indexes:
        raise RuntimeError(f"the models rebuild changed its indexes: {indexes} -> {_indexes(bind)}")
    after = {t: bind.exec_driver_sql(f"SELECT count(*) FROM {t}").scalar() for t in counts}
    if after != counts or linked != bind.exec_driver_sql(
            "SELECT count(*) FROM tracking_sessions WHERE model_id IS NOT NULL").scalar():
        raise RuntimeError(f"the models rebuild changed rows: {counts} -> {after}")
    broken = bind.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
    if broken:
        raise RuntimeError(f"foreign keys broken by the models rebuild: {broken[:5]}")


def upgrade() -> None:
    _rebuild_models(True)


def downgrade() -> None:
    _rebuild_models(False)
