"""Whether the service can do its work: the database answers."""

from __future__ import annotations

from server.db import Database
from server.errors import Unavailable
from server.store.health import ping, touch


class HealthService:
    def __init__(self, db: Database):
        self._db = db

    def check(self) -> None:
        """Raises ``Unavailable`` naming the driver's error when the database does not answer."""
        try:
            with self._db.read() as conn:
                ping(conn)
        except Exception as exc:  # any driver error means "not healthy"
            raise Unavailable(f"database unavailable: {type(exc).__name__}") from None

    def check_writable(self) -> None:
        """Raises ``Unavailable`` when the database cannot commit a write (full, locked, read-only, gone)."""
        try:
            with self._db.write() as conn:
                touch(conn)
        except Exception as exc:  # any driver error means "not ready"
            raise Unavailable(f"database cannot write: {type(exc).__name__}") from None
