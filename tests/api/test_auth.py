"""Scoped bearer keys: 401 without or with an unknown key, 403 with the wrong scope."""

from __future__ import annotations

import httpx
import pytest

from server.auth import create_key
from server.db import Database
from server.store import keys

ADMIN_ENDPOINTS = [
    ("POST", "/api/v1/sites", {"name": "x"}),
    ("GET", "/api/v1/sites", None),
    ("GET", "/api/v1/sites/1", None),
    ("DELETE", "/api/v1/sites/1", None),
    ("PUT", "/api/v1/sites/1/transmitters", []),
    ("GET", "/api/v1/sites/1/transmitters", None),
    ("GET", "/api/v1/sites/1/reference-points", None),
    ("POST", "/api/v1/sites/1/surveys", {"fingerprints": []}),
]


@pytest.mark.parametrize("method, path, body", ADMIN_ENDPOINTS)
def test_admin_endpoints_need_an_admin_key(anonymous, device, snapshot, method, path, body):
    before = snapshot()
    missing = anonymous.request(method, path, json=body)
    assert missing.status_code == 401 and missing.headers["WWW-Authenticate"] == "Bearer"
    unknown = anonymous.request(method, path, json=body, headers={"Authorization": "Bearer not-a-key"})
    assert unknown.status_code == 401 and "unknown" in unknown.json()["detail"]
    wrong_scheme = anonymous.request(method, path, json=body, headers={"Authorization": "Basic YTpi"})
    assert wrong_scheme.status_code == 401
    forbidden = device.request(method, path, json=body)
    assert forbidden.status_code == 403 and "admin" in forbidden.json()["detail"]
    assert snapshot() == before


def test_healthz_needs_no_key(anonymous):
    answer = anonymous.get("/healthz")
    assert answer.status_code == 200 and answer.json() == {"status": "ok"}


def test_keys_created_from_the_cli_work_until_revoked(live_server, clean_db):
    db = Database(clean_db)
    key_id, key = create_key(db, "survey team", "admin")
    with db.transaction() as s:
        assert [k.name for k in keys.list_api_keys(s)] == ["survey team"]
        assert all(key not in (k.key_hash, k.name) for k in keys.list_api_keys(s))  # only the hash is stored
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {key}"}) as client:
        assert client.get("/api/v1/sites").status_code == 200
        with db.transaction() as s:
            assert keys.revoke_api_key(s, key_id)
        assert client.get("/api/v1/sites").status_code == 401
    db.dispose()


def test_device_keys_from_the_cli_have_device_scope(live_server, clean_db):
    db = Database(clean_db)
    _, key = create_key(db, "phone 7", "device")
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {key}"}) as client:
        assert client.get("/api/v1/sites").status_code == 403
    db.dispose()
