"""Locate's serving-model memo: a model activated, deleted or changed by any connection (another
server process included) is seen by the very next locate; nothing is remembered across a commit."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import make_url

from server.db import Database
from server.domain import ServingModel
from server.services.positioning import ServingMemo
from tests.api.test_models import SYNTH, site, train  # noqa: F401  (site: the fixture)

ROOT = Path(__file__).resolve().parents[2]


def _activate_elsewhere(database_url: str, site_id: int, model_id: int) -> None:
    """Activate a model from another process, as another server worker would."""
    code = textwrap.dedent(f"""
        from server.db import Database
        from server.store import models
        db = Database({database_url!r})
        with db.transaction() as s:
            models.activate_model(s, {site_id}, {model_id})
        db.dispose()
    """)
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=120)


def test_locate_follows_a_model_activated_by_another_process(admin, device, site, live_server):  # noqa: F811
    first = train(admin, site, algorithm="knn")
    second = train(admin, site, algorithm="wknn")
    assert first["active"] is True and second["active"] is False
    url = f"/api/v1/sites/{site['id']}/locate"
    scan = {"rss": SYNTH.scan(4.0, 4.0, 0, None, np.random.default_rng(1), 1.0)}
    for _ in range(3):  # asked once, then remembered
        assert device.post(url, json=scan).json()["model_id"] == first["id"]

    _activate_elsewhere(live_server.app.state.settings.database_url, site["id"], second["id"])
    answer = device.post(url, json=scan).json()
    assert answer["model_id"] == second["id"] and answer["in_coverage"] is not None  # wknn: coverage measured
    assert device.post(url, json={**scan, "model_id": first["id"]}).json()["model_id"] == first["id"]

    assert admin.delete(f"/api/v1/sites/{site['id']}").status_code == 204
    gone = device.post(url, json=scan)
    assert gone.status_code == 404, gone.text


@pytest.fixture
def sqlite_file(tmp_path) -> str:
    path = tmp_path / "memo.db"
    with sqlite3.connect(path) as conn:
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("CREATE TABLE t (v INTEGER)")
    return str(path)


SERVING = ServingModel(7, "wknn", "ab" * 32)


def test_the_memo_forgets_everything_on_a_commit_by_any_other_connection(sqlite_file):
    memo = ServingMemo(sqlite_file)
    version = memo.version()
    assert version is not None
    memo.put(version, (1, None), SERVING)
    assert memo.version() == version and memo.get(version, (1, None)) == SERVING
    assert memo.get(version, (1, 7)) is None and memo.get(version, (2, None)) is None

    with sqlite3.connect(sqlite_file) as other:  # e.g. a session's batch: any table, any commit
        other.execute("INSERT INTO t VALUES (1)")
    newer = memo.version()
    assert newer is not None and newer != version
    assert memo.get(newer, (1, None)) is None


def test_an_answer_read_before_a_commit_is_not_kept_after_it(sqlite_file):
    memo = ServingMemo(sqlite_file)
    before = memo.version()
    assert before is not None
    with sqlite3.connect(sqlite_file) as other:
        other.execute("INSERT INTO t VALUES (1)")
    after = memo.version()  # another request saw the commit meanwhile
    assert after is not None
    memo.put(before, (1, None), SERVING)  # the slower request's answer, read under the older version
    assert memo.get(after, (1, None)) is None


def test_the_memo_is_off_where_commits_cannot_be_told(tmp_path):
    assert ServingMemo(None).version() is None
    assert ServingMemo.for_database(Database("sqlite://")).version() is None  # in memory: one per connection
    missing = ServingMemo(str(tmp_path / "none.db"))  # never creates a database
    assert missing.version() is None and not (tmp_path / "none.db").exists()


def test_the_memo_is_on_for_the_servers_sqlite_file(database_url):
    memo = ServingMemo.for_database(Database(database_url))
    if make_url(database_url).get_backend_name() == "sqlite":
        assert memo.version() is not None
    else:
        assert memo.version() is None


def test_the_memo_opens_a_path_that_needs_quoting_in_a_uri(tmp_path):
    path = tmp_path / "a site #1 ?100%.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE t (v INTEGER)")
    assert ServingMemo(str(path)).version() is not None
