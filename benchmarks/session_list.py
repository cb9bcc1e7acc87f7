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
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.bench_site import bench_site, open_session, timed_get  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=1000)
    ap.add_argument("--filter", default="pf")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--database-url", default=None, help="default: SQLite in a temporary folder")
    ap.add_argument("--port", type=int, default=8794)
    a = ap.parse_args()
    with bench_site(a.port, a.database_url, "list") as site:
        admin, dev = site.admin, site.device
        steps = [{"t": 0.5 * i, "length_m": 0.7, "heading_deg": 90.0} for i in range(4)]
        for _ in range(a.sessions):
            sid = open_session(site, a.filter)
            dev.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "steps": steps}).raise_for_status()
        health, own, every = [], [], []
        for _ in range(a.repeat):
            health += [timed_get(dev, "/healthz")[0] for _ in range(20)]
            dt, r = timed_get(dev, f"/api/v1/sessions?limit={a.sessions}")
            assert len(r.json()) == a.sessions
            own.append(dt)
            dt, r = timed_get(admin, f"/api/v1/sessions?limit={a.sessions}")
            assert len(r.json()) >= a.sessions
            every.append(dt)
    h = statistics.median(health) * 1e3
    o, e = statistics.median(own) * 1e3, statistics.median(every) * 1e3
    print(f"{a.sessions} {a.filter} sessions, {'SQLite' if a.database_url is None else a.database_url}, "
          f"median of {a.repeat} lists")
    print(f"baseline GET /healthz: {h:.2f} ms")
    print(f"list (device key, its own): {o:.1f} ms ({o / h:.1f}x healthz)")
    print(f"list (admin key, every session): {e:.1f} ms ({e / h:.1f}x healthz)")


if __name__ == "__main__":
    main()
