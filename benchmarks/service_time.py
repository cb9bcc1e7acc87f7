"""In-process service time of a tracking batch and of a locate, through the real app.

Run from the repository root:
    python benchmarks/service_time.py [--batches N] [--filter skpf] [--database-url URL] [--profile FILE]

The app runs in this process (Starlette's TestClient: no sockets, no client load
generator) on a fresh SQLite database (or ``--database-url``) with a small synthetic site and
a KNN model. It
prints µs per request for ``GET /healthz`` (the baseline: the HTTP stack and key check
alone), a tracking batch (5 steps and 1 scan) and a ``locate``, each as a ratio against
the baseline measured in the same run, then the same batch and locate as direct calls of
the session and positioning services (no HTTP: the service time itself). ``--profile``
writes a cProfile of as many more service batches (``python -m pstats FILE``).
"""

from __future__ import annotations

import argparse
import cProfile
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastapi.testclient import TestClient  # noqa: E402

from server import migrate  # noqa: E402
from server.app import create_app  # noqa: E402
from server.config import Settings  # noqa: E402
from server.estimation.types import Scan, Step  # noqa: E402

APS = {f"wifi:ap{i}": (x, y) for i, (x, y) in enumerate([(0, 0), (30, 0), (0, 20), (30, 20), (15, 10), (15, 0)])}


def rss_at(x: float, y: float) -> dict[str, float]:
    """Log-distance RSS of the site's APs at (x, y), rounded to whole dBm."""
    return {k: round(-40.0 - 25.0 * math.log10(max(math.hypot(x - ax, y - ay), 1.0))) for k, (ax, ay) in APS.items()}


def _per_call_us(fn, n: int) -> list[float]:
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append((time.perf_counter() - t0) * 1e6)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, default=400)
    ap.add_argument("--locates", type=int, default=400)
    ap.add_argument("--filter", default="skpf")
    ap.add_argument("--database-url", help="default: a new SQLite file (a PostgreSQL database may be used again)")
    ap.add_argument("--profile", metavar="FILE", help="also write a cProfile of the service batches to FILE")
    args = ap.parse_args()

    url = args.database_url or f"sqlite:///{tempfile.mkdtemp()}/bench.db"
    migrate.upgrade(url)
    settings = Settings(database_url=url, admin_keys=["a"], device_keys=["d"], embedded_worker=True, training_poll_s=0.2)
    app = create_app(settings)
    with TestClient(app) as client:
        admin, device = {"Authorization": "Bearer a"}, {"Authorization": "Bearer d"}
        site = client.post("/api/v1/sites", json={"name": f"bench {time.time_ns()}"}, headers=admin).json()["id"]
        grid = [(float(x), float(y)) for x in range(0, 31, 2) for y in range(0, 21, 2)]
        survey = [{"x": x, "y": y, "floor": 0, "rss": rss_at(x, y)} for x, y in grid]
        r = client.post(f"/api/v1/sites/{site}/surveys", json={"fingerprints": survey}, headers=admin)
        r.raise_for_status()
        model = client.post(f"/api/v1/sites/{site}/models", json={"algorithm": "knn"}, headers=admin).json()["id"]
        deadline = time.monotonic() + 120
        while client.get(f"/api/v1/sites/{site}/models/{model}", headers=admin).json()["status"] != "ready":
            if time.monotonic() > deadline:
                raise SystemExit("the model did not train")
            time.sleep(0.2)

        session = client.post("/api/v1/sessions", json={
            "site_id": site, "filter": args.filter, "initial": {"x": 1.0, "y": 10.0, "floor": 0},
        }, headers=device).json()["id"]

        def batch(i: int) -> None:
            t0 = i * 5 * 0.5
            x = 1.0 + (0.7 * 5 * i) % 28
            steps = [{"t": t0 + k * 0.5, "length_m": 0.7, "heading_deg": 90.0} for k in range(5)]
            scans = [{"t": t0 + 2.4, "rss": rss_at(x, 10.0)}]
            r = client.post(f"/api/v1/sessions/{session}/batches", json={"seq": i, "steps": steps, "scans": scans},
                            headers=device)
            assert r.status_code == 200, r.text

        def locate(i: int) -> None:
            r = client.post(f"/api/v1/sites/{site}/locate", json={"rss": rss_at(i % 30, (i * 7) % 20)}, headers=device)
            assert r.status_code == 200, r.text

        def health(_: int) -> None:
            assert client.get("/healthz", headers=device).status_code == 200

        sessions, positioning = app.state.sessions, app.state.positioning
        principal = app.state.auth.bootstrap("d")

        def service_batch(i: int) -> None:
            """The session service alone: read, apply_batch, compare-and-set write (no HTTP)."""
            seq = args.batches + i
            t0 = seq * 5 * 0.5
            steps = [Step(t0 + k * 0.5, 0.7, 90.0) for k in range(5)]
            sessions.feed(principal, session, seq, steps, [Scan(t0 + 2.4, rss_at(1.0 + (3.5 * i) % 28, 10.0))])

        def service_locate(i: int) -> None:
            positioning.locate(site, rss_at(i % 30, (i * 7) % 20))

        locate(0)  # load the model into the cache
        health_us = _per_call_us(health, args.batches)
        batch_us = _per_call_us(batch, args.batches)
        locate_us = _per_call_us(locate, args.locates)
        service_batch_us = _per_call_us(service_batch, args.batches)
        if args.profile:
            with cProfile.Profile() as profile:
                for i in range(args.batches):
                    service_batch(args.batches + i)
            profile.dump_stats(args.profile)
        service_locate_us = _per_call_us(service_locate, args.locates)

    base = statistics.median(health_us)
    print(f"{'request':<15} {'median µs':>10} {'p90 µs':>10} {'× healthz':>10}")
    rows = (("healthz", health_us), ("batch", batch_us), ("locate", locate_us),
            ("service batch", service_batch_us), ("service locate", service_locate_us))
    for name, xs in rows:
        p90 = statistics.quantiles(xs, n=10)[-1]
        print(f"{name:<15} {statistics.median(xs):>10.0f} {p90:>10.0f} {statistics.median(xs) / base:>10.2f}")


if __name__ == "__main__":
    main()
