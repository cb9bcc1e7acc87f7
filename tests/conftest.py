"""Shared fixtures: a migrated database (SQLite by default, PostgreSQL when
LOCALIZER_TEST_DATABASE_URL is set) and a real uvicorn server on a free port."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
import uvicorn
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from server import migrate
from server.app import create_app
from server.config import Settings
from server.tables import Base

ADMIN_KEY = "test-admin-key"
DEVICE_KEY = "test-device-key"


def _ensure_postgres_database(url: str) -> None:
    """Create the target database if the server lacks it (CI starts from a bare cluster)."""
    target = make_url(url)
    engine = create_engine(target.set(database="postgres"), isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        exists = conn.scalar(text("SELECT 1 FROM pg_database WHERE datname = :n"), {"n": target.database})
        if not exists:
            conn.execute(text(f'CREATE DATABASE "{target.database}"'))
    engine.dispose()


def reset_postgres_database(url: str) -> None:
    """An empty PostgreSQL database at ``url``: created if missing, its public schema dropped."""
    _ensure_postgres_database(url)
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.execute(text("DROP SCHEMA public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    engine.dispose()


@pytest.fixture(scope="session")
def database_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    url = os.environ.get("LOCALIZER_TEST_DATABASE_URL")
    if url:
        reset_postgres_database(url)
    else:
        url = f"sqlite:///{tmp_path_factory.mktemp('db') / 'test.db'}"
    migrate.upgrade(url)
    return url


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LiveServer:
    """uvicorn serving the app in a background thread."""

    def __init__(self, settings: Settings):
        self.app = create_app(settings)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self._server = uvicorn.Server(uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning"))
        self._thread = threading.Thread(target=self._server.run, daemon=True)

    def start(self) -> LiveServer:
        self._thread.start()
        deadline = time.monotonic() + 20
        while not self._server.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise RuntimeError("test server did not start")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        self._thread.join(timeout=10)


def make_settings(database_url: str, **overrides) -> Settings:
    return Settings(database_url=database_url, admin_keys=[ADMIN_KEY], device_keys=[DEVICE_KEY], **overrides)


@pytest.fixture(scope="session")
def live_server(database_url: str) -> Iterator[LiveServer]:
    server = LiveServer(make_settings(database_url, max_body_mb=8, max_survey_rows=5000)).start()
    yield server
    server.stop()


def scratch_database_url(tmp_path, name: str) -> str:
    """A fresh empty database of its own: SQLite in ``tmp_path``, or a PostgreSQL database
    ``<test database>_<name>`` beside the test one (emptied first)."""
    url = os.environ.get("LOCALIZER_TEST_DATABASE_URL")
    if not url:
        return f"sqlite:///{tmp_path / f'{name}.db'}"
    url = make_url(url).set(database=f"{make_url(url).database}_{name}").render_as_string(hide_password=False)
    reset_postgres_database(url)
    return url


@pytest.fixture
def own_db(tmp_path) -> str:
    """A migrated database no other test and no live server uses (the shared live server's
    embedded training worker claims queued models in the shared one)."""
    url = scratch_database_url(tmp_path, "own")
    migrate.upgrade(url)
    return url


@pytest.fixture
def clean_db(database_url: str) -> Iterator[str]:
    """Empty every table after the test, so each API test starts from nothing."""
    yield database_url
    engine = create_engine(database_url)
    with engine.begin() as conn:
        for table in reversed(Base.metadata.sorted_tables):
            conn.execute(table.delete())
    engine.dispose()


def _client(server: LiveServer, key: str | None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    return httpx.Client(base_url=server.url, headers=headers, timeout=60)


@pytest.fixture
def admin(live_server: LiveServer, clean_db: str) -> Iterator[httpx.Client]:
    with _client(live_server, ADMIN_KEY) as client:
        yield client


@pytest.fixture
def device(live_server: LiveServer, clean_db: str) -> Iterator[httpx.Client]:
    with _client(live_server, DEVICE_KEY) as client:
        yield client


@pytest.fixture
def anonymous(live_server: LiveServer, clean_db: str) -> Iterator[httpx.Client]:
    with _client(live_server, None) as client:
        yield client


@pytest.fixture
def snapshot(clean_db: str):
    """A function returning every stored row, to prove a rejected request changed nothing."""

    def take() -> dict[str, list[tuple]]:
        engine = create_engine(clean_db)
        with engine.connect() as conn:
            rows = {t.name: sorted(map(repr, conn.execute(t.select()))) for t in Base.metadata.sorted_tables}
        engine.dispose()
        return rows

    return take
