"""A real server process on a fresh database with one empty one-floor site, for the HTTP
read benchmarks (``track_pages.py``, ``session_list.py``); the server's CPU time, a cost that
other work on a shared machine does not inflate the way it does wall-clock times."""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import httpx

from client_sim.server_process import start_server, stop_server

ADMIN, DEVICE = "bench-admin", "bench-device"


@dataclass(frozen=True)
class BenchSite:
    database_url: str
    admin: httpx.Client
    device: httpx.Client
    site_id: int
    server_pid: int

    def server_cpu_s(self) -> float:
        """CPU seconds (user + system) the server process has used so far (Linux ``/proc``)."""
        with open(f"/proc/{self.server_pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@contextmanager
def bench_site(port: int, database_url: str | None, name: str) -> Iterator[BenchSite]:
    """The server (SQLite in a temporary folder unless ``database_url``), an admin and a
    device client, and a new site with floor 0; the server stops on leaving."""
    with tempfile.TemporaryDirectory() as tmp:
        url = database_url or f"sqlite:///{tmp}/bench.db"
        server = start_server(port, {"LOCALIZER_DATABASE_URL": url, "LOCALIZER_ADMIN_KEYS": ADMIN,
                                     "LOCALIZER_DEVICE_KEYS": DEVICE})
        base = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {ADMIN}"}, timeout=120) as admin, \
                    httpx.Client(base_url=base, headers={"Authorization": f"Bearer {DEVICE}"}, timeout=120) as dev:
                site = admin.post("/api/v1/sites", json={"name": f"{name}-{time.time_ns()}", "floors": [{"level": 0}]})
                site.raise_for_status()
                yield BenchSite(url, admin, dev, site.json()["id"], server.pid)
        finally:
            stop_server(server)


def open_session(site: BenchSite, filter: str) -> str:
    """A device session on the site, started at the origin; its id."""
    opened = site.device.post("/api/v1/sessions", json={"site_id": site.site_id, "filter": filter,
                                                        "initial": {"x": 0.0, "y": 0.0, "floor": 0}})
    opened.raise_for_status()
    return opened.json()["id"]


def timed_get(http: httpx.Client, url: str) -> tuple[float, httpx.Response]:
    """Seconds taken by ``GET url``, and the answer."""
    t0 = time.perf_counter()
    r = http.get(url)
    return time.perf_counter() - t0, r
