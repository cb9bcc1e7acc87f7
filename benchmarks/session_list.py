"""What listing sessions costs through HTTP: ``GET /api/v1/sessions?limit=1000`` over PF sessions.

    python benchmarks/session_list.py [--sessions 1000] [--filter pf] [--database-url URL]

Starts a real server process (SQLite in a temporary folder unless ``--database-url``),
opens ``--sessions`` sessions of ``--filter`` with one device key and feeds each one batch
(so each holds a real tracker state and a track), then lists them all, with the device
key (its own sessions, the owner index) and with an admin key (every session, the
``(created_at, id)`` index), in ``--repeat`` rounds of 100 ``GET /healthz`` (the baseline,
in the same run), 5 own and 5 admin lists. Prints the median of each kind and the ratios,
and the server process's CPU time per request (user + system, from ``/proc``: what a
request costs, which other work on a shared machine inflates far less than wall-clock
times).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.bench_site import bench_site, open_session, timed_get  # noqa: E402

#: healthz requests per round (5 lists of each kind): enough server CPU to measure at the clock's 10 ms resolution
HEALTH_PER_ROUND = 100


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=1000)
    ap.add_argument("--filter", default="pf")
    ap.add_argument("--repeat", type=int, default=5, help="rounds of 100 healthz, 5 own and 5 admin lists")
    ap.add_argument("--database-url", default=None, help="default: SQLite in a temporary folder")
    ap.add_argument("--port", type=int, default=8794)
    a = ap.parse_args()
    with bench_site(a.port, a.database_url, "list") as site:
        admin, dev = site.admin, site.device
        steps = [{"t": 0.5 * i, "length_m": 0.7, "heading_deg": 90.0} for i in range(4)]
        for _ in range(a.sessions):
            sid = open_session(site, a.filter)
            dev.post(f"/api/v1/sessions/{sid}/batches", json={"seq": 0, "steps": steps}).raise_for_status()
        urls = {"healthz": (dev, "/healthz", HEALTH_PER_ROUND), "own": (dev, f"/api/v1/sessions?limit={a.sessions}", 5),
                "every": (admin, f"/api/v1/sessions?limit={a.sessions}", 5)}
        walls: dict[str, list[float]] = {kind: [] for kind in urls}
        cpu = dict.fromkeys(urls, 0.0)  # server CPU seconds spent on each kind
        for _ in range(a.repeat):
            for kind, (client, url, n) in urls.items():  # runs of one kind: each run's CPU is its own
                c0 = site.server_cpu_s()
                for _ in range(n):
                    dt, r = timed_get(client, url)
                    r.raise_for_status()
                    walls[kind].append(dt)
                cpu[kind] += site.server_cpu_s() - c0
            assert len(r.json()) >= a.sessions
        health, own, every = walls["healthz"], walls["own"], walls["every"]
    h = statistics.median(health) * 1e3
    o, e = statistics.median(own) * 1e3, statistics.median(every) * 1e3
    ch = cpu["healthz"] / len(health) * 1e3
    co, ce = cpu["own"] / len(own) * 1e3, cpu["every"] / len(every) * 1e3
    print(f"{a.sessions} {a.filter} sessions, {'SQLite' if a.database_url is None else a.database_url}, "
          f"median of {len(own)} lists of each kind (server CPU: mean per request)")
    print(f"baseline GET /healthz: {h:.2f} ms (server CPU {ch:.2f} ms)")
    print(f"list (device key, its own): {o:.1f} ms ({o / h:.1f}x healthz; server CPU {co:.1f} ms, {co / ch:.1f}x)")
    print(f"list (admin key, every session): {e:.1f} ms ({e / h:.1f}x healthz; server CPU {ce:.1f} ms, {ce / ch:.1f}x)")


if __name__ == "__main__":
    main()
