"""``python -m server`` as an operator runs it: migrate, serve (real process), keys; the evaluation CLI starts."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
from sqlalchemy import create_engine, inspect

from tests.conftest import free_port

ROOT = Path(__file__).resolve().parent.parent


def run_cli(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "server", *args], cwd=ROOT, env={**os.environ, **env},
        capture_output=True, text=True, timeout=120,
    )


def test_migrate_creates_the_schema(tmp_path):
    url = f"sqlite:///{tmp_path / 'cli.db'}"
    result = run_cli("migrate", env={"LOCALIZER_DATABASE_URL": url})
    assert result.returncode == 0, result.stderr
    assert "sites" in inspect(create_engine(url)).get_table_names()


def test_keys_create_list_revoke(tmp_path):
    env = {"LOCALIZER_DATABASE_URL": f"sqlite:///{tmp_path / 'keys.db'}"}
    created = run_cli("keys", "create", "--scope", "device", "--name", "kiosk", env=env)
    assert created.returncode == 0, created.stderr
    key = created.stdout.strip().splitlines()[-1]
    assert key.startswith("lk_") and len(key) > 40
    listed = run_cli("keys", "list", env=env).stdout
    assert "device" in listed and "kiosk" in listed and "active" in listed and key not in listed
    assert run_cli("keys", "revoke", "1", env=env).returncode == 0
    assert "revoked" in run_cli("keys", "list", env=env).stdout
    assert run_cli("keys", "revoke", "1", env=env).returncode == 1


def test_serve_migrates_and_answers_over_http(tmp_path):
    port = free_port()
    env = {**os.environ, "LOCALIZER_DATABASE_URL": f"sqlite:///{tmp_path / 'serve.db'}", "LOCALIZER_ADMIN_KEYS": "k1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "server", "serve", "--port", str(port), "--log-level", "warning"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz").json() == {"status": "ok"}:
                    break
            except httpx.TransportError:
                assert process.poll() is None, process.stdout.read().decode()
                assert time.monotonic() < deadline, "server did not come up"
                time.sleep(0.2)
        answer = httpx.post(f"http://127.0.0.1:{port}/api/v1/sites", json={"name": "cli"}, headers={"Authorization": "Bearer k1"})
        assert answer.status_code == 201
    finally:
        process.terminate()
        process.wait(timeout=20)


def test_evaluate_cli_runs_as_a_module():
    result = subprocess.run(
        [sys.executable, "-m", "localizer_tools.evaluate", "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "localizer_tools.evaluate" in result.stdout and "--algorithms" in result.stdout


def test_serve_refuses_a_port_workers_or_log_level_it_cannot_use_before_touching_the_database(tmp_path):
    db = tmp_path / "never.db"
    env = {"LOCALIZER_DATABASE_URL": f"sqlite:///{db}"}
    for args, message in [(("--port", "70000"), "argument --port: must be an integer ≥ 1 and ≤ 65535, not '70000'"),
                          (("--workers", "0"), "argument --workers: must be an integer ≥ 1, not '0'"),
                          (("--log-level", "loud"), "argument --log-level: invalid choice: 'loud'")]:
        result = run_cli("serve", *args, env=env)
        assert result.returncode == 2 and message in result.stderr, (args, result.stderr)
    assert not db.exists()  # refused by the parser: no migration ran
