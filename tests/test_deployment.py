"""docker-compose.yml: PostgreSQL plus two server replicas behind one published port."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = ROOT / "docker-compose.yml"


def compose_command() -> list[str] | None:
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


def test_compose_file_describes_postgres_and_two_replicas_behind_one_port():
    spec = yaml.safe_load(COMPOSE.read_text())
    services = spec["services"]
    assert services["db"]["image"].startswith("postgres")
    server = services["server"]
    assert server["deploy"]["replicas"] == 2
    assert server["environment"]["LOCALIZER_DATABASE_URL"].startswith("postgresql+psycopg://")
    assert "ports" not in server  # replicas are reached only through the proxy
    published = [p for s in services.values() for p in s.get("ports", [])]
    assert len(published) == 1
    assert services["migrate"]["command"][-1] == "migrate"
    assert server["depends_on"]["migrate"]["condition"] == "service_completed_successfully"
    conf = services["proxy"]["volumes"][0].split(":")[0]
    assert "server:8000" in (ROOT / conf).read_text()
    assert (ROOT / "Dockerfile").read_text().count("server\", \"serve\"") == 1


@pytest.mark.skipif(compose_command() is None, reason="no docker compose client on this machine")
def test_docker_compose_config_accepts_the_file():
    result = subprocess.run([*compose_command(), "-f", str(COMPOSE), "config", "-q"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
