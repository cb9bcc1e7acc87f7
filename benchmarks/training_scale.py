"""How training grows with the site: 1k / 5k / 20k / 100k fingerprints, queue to ready.

Each size is a synthetic site of jittered copies of UJIIndoorLoc rows (rows in a random order; the
first copy of each row as it is, later copies with N(0, 2 dB) added to every reading heard,
rounded; positions, buildings, floors and phones kept), stored in a fresh SQLite file
through the store, with a model queued. The clock runs from the queued model to its
``ready`` status through the real training function (`run_training_job` in a spawned
child process, as the server's worker runs it); the peak resident memory is that
child's (``getrusage(RUSAGE_CHILDREN)``); the artifact size is the stored blob's. Each
size runs in its own process, so nothing is shared between sizes.

Printed: a row per size, the growth law between the two largest sizes (time's exponent,
peak memory as a base plus a cost per fingerprint) and the growth ratios 100k/20k (time,
memory) against the targets (≤ 5× and ≤ 1 GB at 100k; 20k ≤ 10 s for the default model).

    .venv/bin/python -m benchmarks.training_scale [--data ../shared/data/ujiindoorloc]
        [--sizes 1000,5000,20000,100000] [--algorithm wknn] [--params '{}']
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import multiprocessing
import resource
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from benchmarks.shared_data import UJIINDOORLOC

ROOT = Path(__file__).resolve().parent.parent


def _records(data: Path, n: int, seed: int = 0) -> list:
    from server.domain import FingerprintRecord
    from server.estimation.fingerprint.loaders import read_ujiindoorloc

    fs = read_ujiindoorloc(str(data / "trainingData.csv"))
    rng = np.random.default_rng(seed)
    has_building = "building" in {f.name for f in dataclasses.fields(FingerprintRecord)}
    order = rng.permutation(len(fs))  # a smaller site: rows drawn at random over the whole campus
    out = []
    for i in range(n):
        j = int(order[i % len(fs)])
        row = fs.rss[j]
        heard = np.flatnonzero(~np.isnan(row))
        values = row[heard] if i < len(fs) else np.clip(np.round(row[heard] + rng.normal(0, 2.0, len(heard))), -110, 0)
        rss = {fs.tx_ids[c]: float(v) for c, v in zip(heard, values, strict=True)}
        b, f = int(fs.building[j]), int(fs.floor[j])
        out.append(FingerprintRecord(
            x=float(fs.x[j]), y=float(fs.y[j]), floor=f if has_building else 10 * b + f, rss=rss,
            device=None if fs.device is None else str(fs.device[j]), building=b if has_building else 0))
    return out


def one_size(data: Path, n: int, algorithm: str, params: dict) -> dict:
    """Store a site of ``n`` fingerprints, queue a model, time it to ready (this process's child)."""
    from server import migrate
    from server.db import Database
    from server.domain import ModelSpec, NewSite
    from server.services.training import run_training_job
    from server.store import models as model_store
    from server.store import sites as site_store
    from server.store import surveys as survey_store
    from server.tables import ModelArtifact

    records = _records(data, n)
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/scale.db"
        migrate.upgrade(url)
        db = Database(url)
        with db.transaction() as s:
            site = site_store.add_site(s, NewSite(name=f"scale {n}"))
            for k in range(0, n, 5000):
                survey_store.add_survey(s, site.id, records[k: k + 5000], None, 0)
        del records
        with db.transaction() as s:
            model_id = model_store.add_model(s, site.id, ModelSpec(algorithm, params)).id
        t0 = time.perf_counter()
        with db.transaction() as s:  # what the worker does: claim, then train in a spawned child
            assert model_store.claim_next_model(s, datetime.now(UTC) - timedelta(minutes=5)) == model_id
        child = multiprocessing.get_context("spawn").Process(target=run_training_job, args=(url, model_id))
        child.start()
        child.join()
        seconds = time.perf_counter() - t0
        peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        with db.transaction() as s:
            model = model_store.get_model(s, site.id, model_id)
            blob = s.get(ModelArtifact, model_id)
            size = 0 if blob is None else len(blob.blob)
        db.dispose()
    assert model is not None
    if model.status != "ready":
        raise SystemExit(f"model {model_id} is {model.status}: {model.error}")
    m = dict(model.metrics or {})
    return {"n": n, "seconds": seconds, "peak_mb": peak_mb, "artifact_mb": size / 1e6,
            "mean_error_m": m.get("mean_error_m"), "floor_hit_rate": m.get("floor_hit_rate"),
            "building_hit_rate": m.get("building_hit_rate"), "validated_on": m.get("validated_on"),
            "fit_time_s": m.get("fit_time_s")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=UJIINDOORLOC,
                    help="folder with UJIIndoorLoc's trainingData.csv (default %(default)s)")
    ap.add_argument("--sizes", default="1000,5000,20000,100000", help="fingerprint counts (default %(default)s)")
    ap.add_argument("--algorithm", default="wknn", help="algorithm trained (default %(default)s)")
    ap.add_argument("--params", default="{}", help="model parameters as JSON (default %(default)s)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: run one size, print its JSON
    a = ap.parse_args(argv)
    params = json.loads(a.params)
    if a.one:
        print(json.dumps(one_size(a.data, a.one, a.algorithm, params)))
        return 0
    rows = []
    print(f"{a.algorithm} {params}: queue → ready through run_training_job, jittered UJIIndoorLoc rows from {a.data}")
    print("| fingerprints | queue → ready s | peak MB | artifact MB | held-out mean m | floor | building | validated on |")
    print("|---|---|---|---|---|---|---|---|")
    for n in (int(v) for v in a.sizes.split(",")):
        out = subprocess.run([sys.executable, "-m", "benchmarks.training_scale", "--one", str(n), "--data", str(a.data),
                              "--algorithm", a.algorithm, "--params", a.params],
                             cwd=ROOT, capture_output=True, text=True, check=False)
        if out.returncode != 0:
            print(out.stderr[-3000:], file=sys.stderr)
            return 1
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        pct = lambda v: "–" if v is None else f"{100 * v:.1f} %"  # noqa: E731
        print(f"| {r['n']:,} | {r['seconds']:.1f} | {r['peak_mb']:.0f} | {r['artifact_mb']:.1f} | "
              f"{r['mean_error_m'] or float('nan'):.2f} | {pct(r['floor_hit_rate'])} | {pct(r['building_hit_rate'])} "
              f"| {r['validated_on']} |", flush=True)
    by_n = {r["n"]: r for r in rows}
    if len(rows) >= 2:  # from the two largest sizes
        small, large = sorted(rows, key=lambda r: r["n"])[-2:]
        exponent = math.log(large["seconds"] / small["seconds"]) / math.log(large["n"] / small["n"])
        per_fp_kb = (large["peak_mb"] - small["peak_mb"]) * 1024 / (large["n"] - small["n"])
        base_mb = large["peak_mb"] - per_fp_kb * large["n"] / 1024
        print(f"growth law ({small['n']:,} → {large['n']:,}): time ∝ n^{exponent:.2f}; "
              f"peak ≈ {base_mb:.0f} MB + {per_fp_kb:.1f} KB per fingerprint")
    if 20000 in by_n and 100000 in by_n:
        big, mid = by_n[100000], by_n[20000]
        print(f"growth 100k/20k: time {big['seconds'] / mid['seconds']:.2f}× (target ≤ 5×), "
              f"memory {big['peak_mb'] / mid['peak_mb']:.2f}×; peak at 100k {big['peak_mb']:.0f} MB (target ≤ 1,024)")
    if 20000 in by_n:
        print(f"20k queue → ready: {by_n[20000]['seconds']:.1f} s (target ≤ 10 s for the default model)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
