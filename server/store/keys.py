"""API keys created from the CLI, stored by their SHA-256 only."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import cast

from sqlalchemy import Connection, bindparam, select, update
from sqlalchemy.orm import Session

from server.domain import ApiKeyInfo, Scope
from server.store._direct import DirectStatement
from server.store._results import changed
from server.tables import ApiKey


def _info(key: ApiKey) -> ApiKeyInfo:
    return ApiKeyInfo(
        id=key.id, name=key.name, scope=cast(Scope, key.scope), key_hash=key.key_hash,
        created_at=key.created_at, revoked_at=key.revoked_at,
    )


def add_api_key(s: Session, name: str, scope: Scope, key_hash: str) -> ApiKeyInfo:
    key = ApiKey(name=name, scope=scope, key_hash=key_hash)
    s.add(key)
    s.flush()
    return _info(key)


#: on the driver's cursor (``_direct``): a stored key is looked up on every request that sends one
_KEY_SCOPE = DirectStatement(select(ApiKey.scope).where(ApiKey.key_hash == bindparam("key_hash"),
                                                       ApiKey.revoked_at.is_(None)))


def key_scope(conn: Connection, key_hash: str) -> Scope | None:
    """The scope of the key with this hash, unless it was revoked."""
    row = _KEY_SCOPE.first(conn, {"key_hash": key_hash})
    return None if row is None else cast(Scope, row[0])


def list_api_keys(s: Session) -> list[ApiKeyInfo]:
    return [_info(key) for key in s.scalars(select(ApiKey).order_by(ApiKey.id))]


def revoke_api_key(s: Session, key_id: int) -> bool:
    """False when there is no such key, or it was already revoked."""
    result = s.execute(
        update(ApiKey)
        .where(ApiKey.id == key_id, ApiKey.revoked_at.is_(None))
        .values(revoked_at=datetime.now(UTC))
    )
    return changed(result) == 1
