"""How long the UJIIndoorLoc training file takes to upload through the HTTP API.

    python benchmarks/upload_ujiindoorloc.py ../shared/data/ujiindoorloc/trainingData.csv

Starts a real server process (``python -m server serve``) on a fresh SQLite file (or
``--database-url``), creates a site and runs the upload tool twice: with its validation
pass (the default) and without. The baseline, timed in the same process, is a plain
``csv.reader`` pass over the file, so the ratio says how much the service adds to reading it.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from client_sim.server_process import start_server, stop_server  # noqa: E402
from localizer_tools.upload import upload  # noqa: E402

KEY = "benchmark-admin-key"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="UJIIndoorLoc trainingData.csv")
    parser.add_argument("--database-url", help="default: a new SQLite file")
    parser.add_argument("--port", type=int, default=8791)
    args = parser.parse_args()

    started = time.perf_counter()
    with args.data.open(newline="") as f:
        rows = sum(1 for _ in csv.reader(f)) - 1
    baseline = time.perf_counter() - started

    with tempfile.TemporaryDirectory() as tmp:
        url = args.database_url or f"sqlite:///{tmp}/bench.db"
        server = start_server(args.port, {"LOCALIZER_DATABASE_URL": url, "LOCALIZER_ADMIN_KEYS": KEY})
        base = f"http://127.0.0.1:{args.port}"
        try:
            results = []
            for name, validate in (("validate, then store", True), ("store only (--no-validate)", False)):
                site = httpx.post(
                    f"{base}/api/v1/sites", json={"name": f"uji {name}"}, headers={"Authorization": f"Bearer {KEY}"}
                ).json()
                out = io.StringIO()
                t0 = time.perf_counter()
                code = upload(args.data, base, KEY, site["id"], "ujiindoorloc", progress=False, validate_first=validate, out=out)
                seconds = time.perf_counter() - t0
                if code != 0:
                    raise SystemExit(out.getvalue())
                results.append((name, seconds, out.getvalue().strip()))
        finally:
            stop_server(server)

    print(f"file: {args.data} ({rows} rows); database: {'SQLite' if not args.database_url else args.database_url.split(':')[0]}")
    print(f"baseline (csv.reader over the file, same process): {baseline:.2f} s")
    print(f"{'upload':<28} {'seconds':>8} {'rows/s':>8} {'x baseline':>10}")
    for name, seconds, _ in results:
        print(f"{name:<28} {seconds:8.2f} {rows / seconds:8.0f} {seconds / baseline:10.1f}")
    print(results[0][2])


if __name__ == "__main__":
    main()
