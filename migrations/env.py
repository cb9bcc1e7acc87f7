"""Alembic environment: the URL comes from the caller or from LOCALIZER_DATABASE_URL.

On PostgreSQL the upgrade holds an advisory lock, so replicas starting together migrate once.
On SQLite foreign keys are off while migrations run (table rebuilds must not cascade).
"""

from alembic import context
from sqlalchemy import text

from server.config import get_settings
from server.db import make_engine
from server.tables import Base

MIGRATION_LOCK = 7_130_501
config = context.config
url = config.get_main_option("sqlalchemy.url") or get_settings().database_url


def run(connection) -> None:
    context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
    with context.begin_transaction():
        if connection.dialect.name == "postgresql":
            connection.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": MIGRATION_LOCK})
        context.run_migrations()


if context.is_offline_mode():
    context.configure(url=url, target_metadata=Base.metadata, literal_binds=True, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()
else:
    engine = make_engine(url)
    with engine.connect() as connection:
        sqlite = connection.dialect.name == "sqlite"
        if sqlite:
            # SQLite rebuilds tables to alter them: with foreign keys on, dropping the old table
            # would cascade-delete its children. Off for the migration (only outside a transaction).
            connection.exec_driver_sql("PRAGMA foreign_keys=OFF")
            connection.commit()
        try:
            run(connection)
            if connection.in_transaction():
                connection.commit()
        finally:
            if sqlite:
                connection.exec_driver_sql("PRAGMA foreign_keys=ON")
                connection.commit()
    engine.dispose()
