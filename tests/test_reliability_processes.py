"""Process-level reliability: a real ``python -m server serve`` stopped with SIGTERM or SIGINT
(to its whole process group, as Ctrl-C or systemd do) never fails a model it trained or
was training: a ready model stays ready and active, an interrupted one goes back to the queue."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy import create_engine, text

from tests.conftest import free_port
from tests.helpers.synthetic import make_site

ROOT = Path(__file__).resolve().parent.parent
KEY = "reliability-admin"


class Server:
    def __init__(self, db_path: Path):
        self.db_url = f"sqlite:///{db_path}"
        self.port = free_port()
        env = {**os.environ, "LOCALIZER_DATABASE_URL": self.db_url, "LOCALIZER_ADMIN_KEYS": KEY,
               "LOCALIZER_TRAINING_POLL_S": "0.1"}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "server", "serve", "--port", str(self.port), "--log-level", "warning"],
            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
        )
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", headers={"Authorization": f"Bearer {KEY}"},
                                   timeout=60)
        deadline = time.monotonic() + 60
        while True:
            try:
                if self.client.get("/healthz").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            assert self.process.poll() is None and time.monotonic() < deadline, "server did not come up"
            time.sleep(0.1)

    def signal_group(self, sig: int) -> None:
        os.killpg(self.process.pid, sig)
        self.process.wait(timeout=60)

    def close(self) -> None:
        self.client.close()
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout=20)


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    running = Server(tmp_path / "reliability.db")
    yield running
    running.close()


def surveyed_site(server: Server) -> int:
    synth = make_site()
    site = server.client.post("/api/v1/sites", json={"name": "sigterm", "floors": [{"level": 0}, {"level": 1}],
                                                     "transmitters": synth.transmitters}).json()
    rows = synth.survey(scans_per_rp=8, seed=1).to_rows()
    for row in rows:
        row.pop("building", None)
    assert server.client.post(f"/api/v1/sites/{site['id']}/surveys", json={"fingerprints": rows}).status_code == 201
    return site["id"]


def stored_model(db_url: str, model_id: int) -> tuple[str, bool]:
    engine = create_engine(db_url)
    with engine.connect() as conn:
        status, active = conn.execute(text("SELECT status, active FROM models WHERE id = :i"), {"i": model_id}).one()
    engine.dispose()
    return status, bool(active)


def wait_status(server: Server, site_id: int, model_id: int, wanted: set[str], timeout_s: float = 90) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = server.client.get(f"/api/v1/sites/{site_id}/models/{model_id}").json()["status"]
        if status in wanted:
            return status
        time.sleep(0.02)
    raise AssertionError(f"model {model_id} never reached {wanted}")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_model_ready_when_the_server_is_stopped_stays_ready_and_active(server, sig):
    site_id = surveyed_site(server)
    model_id = server.client.post(f"/api/v1/sites/{site_id}/models", json={"algorithm": "knn"}).json()["id"]
    assert wait_status(server, site_id, model_id, {"ready", "failed"}) == "ready"
    server.signal_group(sig)  # just after the training finished, while its process may still be ending
    assert stored_model(server.db_url, model_id) == ("ready", True)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_training_interrupted_by_stopping_the_server_goes_back_to_the_queue(server, sig):
    site_id = surveyed_site(server)
    model_id = server.client.post(f"/api/v1/sites/{site_id}/models", json={"algorithm": "knn"}).json()["id"]
    assert wait_status(server, site_id, model_id, {"training", "ready", "failed"}) == "training"
    server.signal_group(sig)  # the training child is still starting (a spawned interpreter importing the models)
    assert stored_model(server.db_url, model_id) == ("queued", False)
