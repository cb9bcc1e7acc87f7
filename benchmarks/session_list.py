"""What listing sessions costs through HTTP: ``GET /api/v1/sessions?limit=1000`` over PF sessions.

    python benchmarks/session_list.py [--sessions 1000] [--filter pf] [--database-url URL]

Starts a real server process (SQLite in a temporary folder unless ``--database-url``),
opens ``--sessions`` sessions of ``--filter`` with one device key and feeds each one batch
(so each holds a real tracker state and a track), then lists them all, with the device
key (its own sessions, the owner index) and with an admin key (every session, the
``(created_at, id)`` index). The baseline, in the same run, is ``GET /healthz``. Prints the
median of ``--repeat`` lists and the ratios.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from client_sim.server_process import start_server, stop_server  # noqa: E402

ADMIN, DEVICE = "bench-admin", "bench-device"


def timed(http: httpx.Client, url: str) -> tuple[float, httpx.Response]:
    t0 = time.perf_counter()
    r = http.get(url)
    return time.perf_counter() - t0, r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=1000)
    ap.add_argument("--filter", default="pf")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--database-url", default=None, help="default: SQLite in a temporary folder")
    ap.add_argument("--port", type=int, default=8794)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        url = a.database_url or f"sqlite:///{tmp}/bench.db"
        server = start_server(a.port, {"LOCALIZER_DATABASE_URL": url, "LOCALIZER_ADMIN_KEYS": ADMIN,
                                       "LOCALIZER_DEVICE_KEYS": DEVICE})
        base = f"http://127.0.0.1:{a.port}"
        try:
            with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {ADMIN}"}, timeout=120) as admin, \
                    httpx.Client(base_url=base, headers={"Authorization": f"Bearer {DEVICE}"}, timeout=120) as dev:
                site = admin.post("/api/v1/sites", json={"name": f"list-{time.time_ns()}",
                                                         "floors": [{"level": 0}]}).json()
                steps = [{"t": 0.5 * i, "length_m": 0.7, "heading_deg": 90.0} for i in range(4)]
                for _ in range(a.sessions):
                    opened = dev.post("/api/v1/sessions", json={"site_id": site["id"], "filter": a.filter,
                                                                "initial": {"x": 0.0, "y": 0.0, "floor": 0}})
                    opened.raise_for_status()
                    dev.post(f"/api/v1/sessions/{opened.json()['id']}/batches",
                             json={"seq": 0, "steps": steps}).raise_for_status()
                health, own, every = [], [], []
                for _ in range(a.repeat):
                    health += [timed(dev, "/healthz")[0] for _ in range(20)]
                    dt, r = timed(dev, f"/api/v1/sessions?limit={a.sessions}")
                    assert len(r.json()) == a.sessions
                    own.append(dt)
                    dt, r = timed(admin, f"/api/v1/sessions?limit={a.sessions}")
                    assert len(r.json()) >= a.sessions
                    every.append(dt)
        finally:
            stop_server(server)
    h = statistics.median(health) * 1e3
    o, e = statistics.median(own) * 1e3, statistics.median(every) * 1e3
    print(f"{a.sessions} {a.filter} sessions, {'SQLite' if a.database_url is None else a.database_url}, "
          f"median of {a.repeat} lists")
    print(f"baseline GET /healthz: {h:.2f} ms")
    print(f"list (device key, its own): {o:.1f} ms ({o / h:.1f}x healthz)")
    print(f"list (admin key, every session): {e:.1f} ms ({e / h:.1f}x healthz)")


if __name__ == "__main__":
    main()
