"""Latency and throughput of ``POST /locate`` through HTTP on a UJIIndoorLoc-size site.

    python benchmarks/locate_http.py ../shared/data/ujiindoorloc/trainingData.csv --algorithm knn

Starts a real server process on a fresh SQLite file, uploads the training file, trains
the model and waits for it, then sends held-back scans (rows of the same file) to
``locate``: first one at a time (latency p50/p99), then from concurrent clients
(fixes per second), alternating with as many ``GET /healthz`` from as many clients in
``ROUNDS`` rounds (the same server's capacity for a request that does next to no work — one
trivial database query, in the thread pool —: the HTTP stack's ceiling, measured in the same run
and interleaved, so the ratio locate / healthz
does not depend on the machine's load, which other work on it changes). The server's own CPU
per request (its processes' user + system time over those rounds) is printed beside: the
closed-loop rates also carry the load generator's CPU, on the same cores, and what else runs.
The in-process baseline is the same model's answer computed directly (no HTTP, no
database): ``locate``, and for a model measuring coverage (wknn) ``locate_covered``,
what the server computes per request; the ratio is what the service adds.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import io
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.http_load import client, closed_loop, cpu_seconds  # noqa: E402
from client_sim.server_process import start_server, stop_server  # noqa: E402
from localizer_tools.upload import upload  # noqa: E402
from server.estimation.fingerprint import from_bytes  # noqa: E402

ADMIN, DEVICE = "bench-admin", "bench-device"
ROUNDS = 4  # closed-loop rounds of locate, each followed by as many healthz


def query_scans(path: Path, n: int, seed: int = 0) -> list[dict[str, float]]:
    """``n`` random rows of the UJIIndoorLoc file as scans (heard transmitters only)."""
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    header, rows = rows[0], rows[1:]
    waps = [(i, "wifi:" + h.lower()) for i, h in enumerate(header) if h.startswith("WAP")]
    scans = [{tx: float(r[i]) for i, tx in waps if r[i] != "100"} for r in rows]
    scans = [s for s in scans if s]
    pick = np.random.default_rng(seed).choice(len(scans), size=n, replace=False)
    return [scans[i] for i in pick]


async def fire(base: str, url: str, scans: list[dict], concurrency: int) -> tuple[float, list[float]]:
    async with client(base, DEVICE, concurrency) as http:
        return await closed_loop(http, lambda i: ("POST", url, {"rss": scans[i]}), len(scans), concurrency)


async def fire_healthz(base: str, count: int, concurrency: int) -> float:
    async with client(base, DEVICE, concurrency) as http:
        return (await closed_loop(http, lambda i: ("GET", "/healthz", None), count, concurrency))[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="UJIIndoorLoc trainingData.csv")
    parser.add_argument("--algorithm", default="knn")
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--concurrency", type=int, default=16)
    parser.add_argument("--workers", type=int, default=2, help="server processes")
    parser.add_argument("--port", type=int, default=8792)
    args = parser.parse_args()

    scans = query_scans(args.data, args.requests)
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/bench.db"
        server = start_server(args.port, {"LOCALIZER_DATABASE_URL": url, "LOCALIZER_ADMIN_KEYS": ADMIN,
                                           "LOCALIZER_DEVICE_KEYS": DEVICE}, args.workers)
        base = f"http://127.0.0.1:{args.port}"
        admin = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {ADMIN}"}, timeout=60)
        try:
            site = admin.post("/api/v1/sites", json={"name": "uji"}).json()
            code = upload(args.data, base, ADMIN, site["id"], "ujiindoorloc", progress=False, validate_first=False,
                          out=io.StringIO())
            assert code == 0
            t0 = time.perf_counter()
            model = admin.post(f"/api/v1/sites/{site['id']}/models", json={"algorithm": args.algorithm}).json()
            while model["status"] not in ("ready", "failed"):
                time.sleep(0.5)
                model = admin.get(f"/api/v1/sites/{site['id']}/models/{model['id']}").json()
            train_s = time.perf_counter() - t0
            if model["status"] != "ready":
                raise SystemExit(f"training failed: {model['error']}")
            locate_url = f"/api/v1/sites/{site['id']}/locate"
            asyncio.run(fire(base, locate_url, scans[:50], 1))  # warm every worker's model cache
            _, serial = asyncio.run(fire(base, locate_url, scans[: args.requests // 4], 1))
            elapsed = health_s = locate_cpu = health_cpu = 0.0
            for r in range(ROUNDS):
                part = scans[r::ROUNDS]
                c0 = cpu_seconds(server.pid) or 0.0
                elapsed += asyncio.run(fire(base, locate_url, part, args.concurrency))[0]
                c1 = cpu_seconds(server.pid) or 0.0
                health_s += asyncio.run(fire_healthz(base, len(part), args.concurrency))
                c2 = cpu_seconds(server.pid) or 0.0
                locate_cpu, health_cpu = locate_cpu + c1 - c0, health_cpu + c2 - c1
            blob = _artifact(url, model["id"])
        finally:
            admin.close()
            stop_server(server)

    direct = from_bytes(blob)
    answer = getattr(direct, "locate_covered", direct.locate)
    t0 = time.perf_counter()
    for scan in scans[:500]:
        answer(scan)
    direct_s = (time.perf_counter() - t0) / 500

    serial_ms = np.array(serial) * 1e3
    print(f"site: {args.data.name}, model {args.algorithm} trained on {model['trained_on']} fingerprints "
          f"(queued → ready in {train_s:.1f} s); server: {args.workers} process(es), SQLite")
    print(f"baseline, model.{getattr(answer, '__name__', 'locate')} in this process: {direct_s * 1e3:.2f} ms per fix")
    print(f"HTTP, one client:  p50 {np.percentile(serial_ms, 50):.2f} ms, p99 {np.percentile(serial_ms, 99):.2f} ms "
          f"({np.percentile(serial_ms, 50) / (direct_s * 1e3):.1f}x baseline)")
    locate_rate, health_rate = len(scans) / elapsed, len(scans) / health_s
    print(f"HTTP, {args.concurrency} concurrent clients: {locate_rate:.0f} fixes/s over {len(scans)} requests; "
          f"healthz {health_rate:.0f} /s; locate / healthz capacity {locate_rate / health_rate:.2f} (target ≥ 0.4)")
    if locate_cpu > 0 and health_cpu > 0:
        print(f"server CPU per request: locate {locate_cpu / len(scans) * 1e3:.2f} ms, healthz "
              f"{health_cpu / len(scans) * 1e3:.2f} ms (healthz / locate {health_cpu / locate_cpu:.2f})")


def _artifact(database_url: str, model_id: int) -> bytes:
    from server.db import Database
    from server.store.models import model_artifact

    db = Database(database_url)
    with db.transaction() as s:
        artifact = model_artifact(s, model_id)
        assert artifact is not None, f"model {model_id} has no artifact"
        blob = artifact.blob
    db.dispose()
    return blob


if __name__ == "__main__":
    main()
