"""Alembic environment: the URL comes from the caller or from LOCALIZER_DATABASE_URL.

On PostgreSQL the upgrade holds an advisory lock, so replicas starting together migrate once.
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
        run(connection)
    engine.dispose()
