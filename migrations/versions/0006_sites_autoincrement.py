"""SQLite: site ids are never reused (AUTOINCREMENT), so a client holding a deleted site's id
cannot write into a new site

SQLite rebuilds the table for this. ``migrations/env.py`` turns foreign keys off around SQLite
migrations: with them on, dropping the old table would cascade-delete every row of the site's
floors, transmitters, surveys, models and sessions. The rebuild keeps every id and checks the
foreign keys before it commits. PostgreSQL sequences never reuse ids: nothing to do there.

Revision ID: 0006_sites_autoincrement
Revises: 0005_upload_requests
Create Date: 2026-12-01 12:40:00
"""
from alembic import op
import sqlalchemy as sa

revision = '0006_sites_autoincrement'
down_revision = '0005_upload_requests'
branch_labels = None
depends_on = None


def _rebuild_sites(autoincrement: bool) -> None:
    bind = op.get_bind()
    if bind.dialect.name != "sqlite":
        return
    if bind.exec_driver_sql("PRAGMA foreign_keys").scalar():
        raise RuntimeError("rebuilding sites with foreign keys on would cascade-delete every site's data")
    with op.batch_alter_table('sites', recreate='always', table_kwargs={'sqlite_autoincrement': autoincrement}):
        pass
    broken = bind.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
    if broken:
        raise RuntimeError(f"foreign keys broken by the sites rebuild: {broken[:5]}")


def upgrade() -> None:
    _rebuild_sites(True)


def downgrade() -> None:
    _rebuild_sites(False)
