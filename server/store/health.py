"""Whether the database answers."""

from __future__ import annotations

from sqlalchemy import Connection, text


def ping(conn: Connection) -> None:
    """One trivial query; raises whatever the driver raises when the database does not answer."""
    conn.execute(text("SELECT 1"))
