"""Servers with their own settings: failed-authentication rate limit, body-read timeout, and a
database that is gone (503 with Retry-After, never a 500; readiness says so)."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import httpx
import pytest

from tests.conftest import ADMIN_KEY, LiveServer, make_settings


@pytest.fixture
def strict_server(clean_db: str) -> Iterator[LiveServer]:
    server = LiveServer(make_settings(clean_db, auth_failures_per_minute=3, body_read_timeout_s=0.5)).start()
    yield server
    server.stop()


def test_wrong_keys_from_one_address_are_429_with_retry_after(strict_server):
    with httpx.Client(base_url=strict_server.url) as client:
        wrong = {"Authorization": "Bearer wrong"}
        assert [client.get("/api/v1/sites", headers=wrong).status_code for _ in range(3)] == [401] * 3
        limited = client.get("/api/v1/sites", headers=wrong)
        assert limited.status_code == 429 and 1 <= int(limited.headers["Retry-After"]) <= 60
        assert client.get("/api/v1/sites", headers={"Authorization": f"Bearer {ADMIN_KEY}"}).status_code == 200


def test_a_body_that_stops_arriving_is_408(strict_server):
    with socket.create_connection(("127.0.0.1", strict_server.port), timeout=10) as sock:
        sock.sendall(b"POST /api/v1/sites HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + ADMIN_KEY.encode()
                     + b"\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n" + b'{"name": "slow", "x')
        started = time.monotonic()
        answer = sock.recv(4096)
    assert answer.startswith(b"HTTP/1.1 408") and time.monotonic() - started < 5


@pytest.fixture
def server_without_database() -> Iterator[LiveServer]:
    server = LiveServer(make_settings("postgresql+psycopg://postgres@127.0.0.1:1/gone", embedded_worker=False)).start()
    yield server
    server.stop()


def test_a_database_that_is_gone_is_503_with_retry_after(server_without_database):
    with httpx.Client(base_url=server_without_database.url, headers={"Authorization": f"Bearer {ADMIN_KEY}"},
                      timeout=30) as client:
        for answer in (client.post("/api/v1/sites", json={"name": "x"}), client.get("/api/v1/sites"),
                       client.get("/readyz"), client.get("/healthz")):
            assert answer.status_code == 503 and int(answer.headers["Retry-After"]) > 0, answer.text
            assert "detail" in answer.json()


def test_readiness_tries_a_write(live_server, clean_db):
    with httpx.Client(base_url=live_server.url) as client:
        assert client.get("/readyz").json() == {"status": "ok"}


def test_oversized_headers_are_431(live_server, clean_db):
    with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {ADMIN_KEY}"}) as client:
        answer = client.get("/api/v1/sites", headers={f"X-Pad-{i}": "p" * 4000 for i in range(10)})
        assert answer.status_code == 431
        assert client.get("/api/v1/sites", headers={"X-Pad": "p" * 4000}).status_code == 200
