"""API keys: stored by hash, found until revoked, revoked once."""

from __future__ import annotations

import pytest
from sqlalchemy.exc import IntegrityError

from server.store import keys


def test_a_key_is_found_by_its_hash_until_it_is_revoked(db):
    with db.transaction() as s:
        added = keys.add_api_key(s, "survey team", "admin", "a" * 64)
    with db.read() as conn:
        assert keys.key_scope(conn, "a" * 64) == added.scope == "admin" and added.revoked_at is None
        assert keys.key_scope(conn, "b" * 64) is None
    with db.transaction() as s:
        assert keys.revoke_api_key(s, added.id)
    with db.read() as conn:
        assert keys.key_scope(conn, "a" * 64) is None
    with db.transaction() as s:
        assert not keys.revoke_api_key(s, added.id)  # already revoked
        assert not keys.revoke_api_key(s, added.id + 1000)  # no such key
        (listed,) = keys.list_api_keys(s)
        assert listed.name == "survey team" and listed.revoked_at is not None


def test_keys_are_listed_in_creation_order(db):
    with db.transaction() as s:
        first = keys.add_api_key(s, "one", "device", "1" * 64)
        second = keys.add_api_key(s, "two", "admin", "2" * 64)
    with db.transaction() as s:
        assert [k.id for k in keys.list_api_keys(s)] == [first.id, second.id]


def test_a_hash_is_stored_once(db):
    with db.transaction() as s:
        keys.add_api_key(s, "one", "device", "c" * 64)
    with pytest.raises(IntegrityError), db.transaction() as s:
        keys.add_api_key(s, "again", "admin", "c" * 64)
