"""Scoped bearer keys: bootstrap keys from settings plus hashed keys created from the CLI."""

from __future__ import annotations

import hashlib
import math
import secrets
import threading
import time
from collections import deque
from dataclasses import dataclass

from server.config import Settings
from server.db import Database
from server.domain import Scope
from server.store import keys as store

SCOPES: tuple[Scope, ...] = ("admin", "device")


def hash_key(key: str) -> str:
    """Keys are 256-bit random tokens, so a plain SHA-256 is a safe stored form."""
    return hashlib.sha256(key.encode()).hexdigest()


def new_key() -> str:
    return "lk_" + secrets.token_urlsafe(32)


@dataclass(frozen=True)
class Principal:
    scope: Scope
    key_hash: str

    def allows(self, scope: Scope) -> bool:
        """Admin keys may do everything a device may; device keys only device work."""
        return self.scope == "admin" or self.scope == scope


class FailureLimiter:
    """Failed authentications per client address in a sliding minute: past ``per_minute`` the
    address waits (429 with Retry-After) before any key it sends is looked up again."""

    WINDOW_S = 60.0
    MAX_ADDRESSES = 10_000

    def __init__(self, per_minute: int):
        self.per_minute = per_minute
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def retry_after(self, address: str) -> int | None:
        """Seconds ``address`` must wait, or None if it may try."""
        now = time.monotonic()
        with self._lock:
            failures = self._failures.get(address)
            if failures is None:
                return None
            while failures and failures[0] <= now - self.WINDOW_S:
                failures.popleft()
            if len(failures) < self.per_minute:
                return None
            return max(1, math.ceil(failures[0] + self.WINDOW_S - now))

    def failed(self, address: str) -> None:
        now = time.monotonic()
        with self._lock:
            if len(self._failures) >= self.MAX_ADDRESSES and address not in self._failures:
                stale = [a for a, f in self._failures.items() if not f or f[-1] <= now - self.WINDOW_S]
                for a in stale:
                    del self._failures[a]
                if len(self._failures) >= self.MAX_ADDRESSES:
                    self._failures.pop(next(iter(self._failures)))
            self._failures.setdefault(address, deque()).append(now)


class Authenticator:
    def __init__(self, settings: Settings, db: Database):
        self._db = db
        self.failures = FailureLimiter(settings.auth_failures_per_minute)
        self._bootstrap: dict[str, Scope] = {hash_key(k): "device" for k in settings.device_keys}
        self._bootstrap.update({hash_key(k): "admin" for k in settings.admin_keys})

    def bootstrap(self, key: str) -> Principal | None:
        """A key from the settings (no database needed)."""
        digest = hash_key(key)
        scope = self._bootstrap.get(digest)
        return Principal(scope, digest) if scope is not None else None

    def stored(self, key: str) -> Principal | None:
        """A key created from the CLI and not revoked (one indexed query, on a read connection)."""
        digest = hash_key(key)
        with self._db.read() as conn:
            scope = store.key_scope(conn, digest)
        return Principal(scope, digest) if scope is not None else None


def create_key(db: Database, name: str, scope: Scope) -> tuple[int, str]:
    """Create and store a key; the plain key is returned once and never stored."""
    key = new_key()
    with db.transaction() as s:
        return store.add_api_key(s, name, scope, hash_key(key)).id, key
