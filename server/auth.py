"""Scoped bearer keys: bootstrap keys from settings plus hashed keys created from the CLI."""

from __future__ import annotations

import hashlib
import secrets
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


class Authenticator:
    def __init__(self, settings: Settings, db: Database):
        self._db = db
        self._bootstrap: dict[str, Scope] = {hash_key(k): "device" for k in settings.device_keys}
        self._bootstrap.update({hash_key(k): "admin" for k in settings.admin_keys})

    def bootstrap(self, key: str) -> Principal | None:
        """A key from the settings (no database needed)."""
        digest = hash_key(key)
        scope = self._bootstrap.get(digest)
        return Principal(scope, digest) if scope is not None else None

    def stored(self, key: str) -> Principal | None:
        """A key created from the CLI and not revoked (one indexed query)."""
        digest = hash_key(key)
        with self._db.transaction() as s:
            found = store.find_api_key(s, digest)
            return Principal(found.scope, digest) if found is not None else None


def create_key(db: Database, name: str, scope: Scope) -> tuple[int, str]:
    """Create and store a key; the plain key is returned once and never stored."""
    key = new_key()
    with db.transaction() as s:
        return store.add_api_key(s, name, scope, hash_key(key)).id, key
