"""The store against the suite's real database (SQLite, or PostgreSQL when
LOCALIZER_TEST_DATABASE_URL is set), emptied after each test."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from server.db import Database
from server.domain import NewSite
from server.store import sites


@pytest.fixture
def db(clean_db: str) -> Iterator[Database]:
    database = Database(clean_db)
    yield database
    database.dispose()


@pytest.fixture
def site_id(db: Database) -> int:
    with db.transaction() as s:
        return sites.add_site(s, NewSite(name="lab")).id
