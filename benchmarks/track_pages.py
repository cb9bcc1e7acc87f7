"""What reading a long track costs through HTTP: pages of ``?since=&limit=`` against the whole.

    python benchmarks/track_pages.py [--estimates 30000] [--page 1000] [--database-url URL]

Starts a real server process (SQLite in a temporary folder unless ``--database-url``),
opens a session and gives it ``--estimates`` stored estimates (written straight into the
store: one batch's worth per 20 estimates, so the pages' ``fix_refused`` marks read real
batch rows), then walks the track page by page following the ``Link`` header, and reads
it whole. The baseline, in the same run, is ``GET /healthz`` (the HTTP stack alone).
Prints per-page and whole-track times (median of ``--repeat`` walks) and their ratios.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.bench_site import bench_site, open_session, timed_get  # noqa: E402


def fill(database_url: str, session_id: str, n: int, per_batch: int = 20) -> None:
    """``n`` estimates on the session's track, ``per_batch`` per stored batch."""
    from sqlalchemy import insert, update

    from server.db import Database
    from server.tables import SessionBatch, TrackEstimate, TrackingSession

    db = Database(database_url)
    with db.transaction() as s:
        stored = s.get(TrackingSession, session_id)
        if stored is None:
            raise SystemExit(f"no session {session_id}")
        start = stored.track_length
        rows, batches = [], []
        for i in range(n):
            seq = i // per_batch
            source = "scan" if i % 4 == 3 else "step"
            rows.append({"session_id": session_id, "idx": start + i, "seq": seq, "t": 0.5 * i, "x": 0.01 * i,
                         "y": 1.0, "floor": 0, "building": 0, "covariance": [[1.0, 0.1], [0.1, 1.2]],
                         "source": source})
            if i % per_batch == 0:
                batches.append({"session_id": session_id, "seq": seq, "answer": {"rejected_fixes": []}})
        s.execute(insert(SessionBatch), batches)
        s.execute(insert(TrackEstimate), rows)
        s.execute(update(TrackingSession).where(TrackingSession.id == session_id)
                  .values(track_length=start + n, last_seq=batches[-1]["seq"]))
    db.dispose()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--estimates", type=int, default=30_000)
    ap.add_argument("--page", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--database-url", default=None, help="default: SQLite in a temporary folder")
    ap.add_argument("--port", type=int, default=8793)
    a = ap.parse_args()
    with bench_site(a.port, a.database_url, "pages") as site:
        sid = open_session(site, "skpf")
        fill(site.database_url, sid, a.estimates)
        dev = site.device
        health, pages, whole, n_pages = [], [], [], 0
        for _ in range(a.repeat):
            health += [timed_get(dev, "/healthz")[0] for _ in range(50)]
            nxt: str | None = f"/api/v1/sessions/{sid}/track?limit={a.page}"
            got, n_pages = 0, 0
            while nxt:
                dt, r = timed_get(dev, nxt)
                r.raise_for_status()
                pages.append(dt)
                got += len(r.json())
                n_pages += 1
                nxt = r.links.get("next", {}).get("url")
            assert got == a.estimates + 1, got  # + the initial position
            dt, r = timed_get(dev, f"/api/v1/sessions/{sid}/track")
            whole.append(dt)
            assert len(r.json()) == got
    h = statistics.median(health) * 1e3
    p50, worst = statistics.median(pages) * 1e3, max(pages) * 1e3
    w = statistics.median(whole) * 1e3
    print(f"track of {a.estimates + 1} estimates, {'SQLite' if a.database_url is None else a.database_url}, "
          f"{n_pages} pages of {a.page}, {a.repeat} walks")
    print(f"baseline GET /healthz: {h:.2f} ms")
    print(f"page of {a.page}: median {p50:.1f} ms, worst {worst:.1f} ms ({p50 / h:.1f}x healthz)")
    print(f"whole track: median {w:.0f} ms ({w / p50:.1f}x a page)")


if __name__ == "__main__":
    main()
