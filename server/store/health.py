"""Whether the database answers, and whether it can write."""

from __future__ import annotations

from sqlalchemy import Connection, text


def ping(conn: Connection) -> None:
    """One trivial query; raises whatever the driver raises when the database does not answer."""
    conn.execute(text("SELECT 1"))


def touch(conn: Connection) -> None:
    """One harmless write (the schema version rewritten as itself): raises what the driver raises
    when the database cannot write (disk full, locked, read-only, gone)."""
    conn.execute(text("UPDATE alembic_version SET version_num = version_num"))
