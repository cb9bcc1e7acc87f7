"""Fingerprinting alone on the MSFT site-1 F1 walks, in process: the interpolated radio map
("rmap") against knn and wknn, per fold of walks.

    .venv/bin/python benchmarks/radiomap_msft.py ../shared/data/msft_site1_f1 [--folds 0,1] \
        [--model rmap '{"weight_power": 4}'] ...

The folds are ``client_sim msft --folds 4``'s: fold k tests the walks i with i % 4 = k
against a map of every other walk's WiFi scans, each placed at its waypoint-interpolated
position (``survey_rows``), one device per walk. Each model is fitted directly (no
server, no training-step calibration: the positions are the same) and locates every scan
of the test walks inside their waypoints' span; errors against the interpolated truth.
rmap's defaults were chosen on folds 0–1 with this script (the README reports folds 2–3,
through the API with ``client_sim msft``); the figures here are the quick look.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from client_sim.msft import read_walk, survey_rows, wifi_scans  # noqa: E402
from client_sim.msft_eval import walk_files  # noqa: E402
from server.estimation.fingerprint import FingerprintSet, make_model  # noqa: E402

FOLDS = 4
DEFAULT_MODELS: list[tuple[str, dict]] = [("knn", {}), ("wknn", {}), ("rmap", {})]


def walks(data_dir: Path) -> list[list[dict]]:
    """Each walk's scans as survey rows (device = the walk)."""
    out = []
    for f in walk_files(data_dir):
        w = read_walk(f)
        out.append(survey_rows(w, wifi_scans(w, 3.0), device=f"msft-{w.name}"))
    return out


def fold_errors(rows: list[list[dict]], k: int, algorithm: str, params: dict) -> tuple[np.ndarray, dict]:
    """Errors (m) of fold ``k``'s test scans, and what the model chose."""
    train = FingerprintSet.from_rows([r for i, w in enumerate(rows) if i % FOLDS != k for r in w])
    test = FingerprintSet.from_rows([r for i, w in enumerate(rows) if i % FOLDS == k for r in w])
    model = make_model(algorithm, params, kinds=["wifi"]).fit(train)
    known = [i for i, s in enumerate(test.scans()) if model.known_transmitters(s)]
    test = test.subset(known)
    pred = model.predict(test)
    chosen = {name: getattr(model, attr) for name, attr in
              (("k", "k_"), ("length_scale_m", "length_scale_m_")) if hasattr(model, attr)}
    return np.hypot(pred.x - test.x, pred.y - test.y), chosen


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--folds", default="0,1", help="comma list of folds (0–3) to measure on")
    ap.add_argument("--model", nargs=2, action="append", metavar=("ALGORITHM", "PARAMS_JSON"),
                    help="a model to measure (repeatable; default knn, wknn and rmap with their defaults)")
    a = ap.parse_args(argv)
    folds = [int(k) for k in a.folds.split(",") if k.strip()]
    if not folds or any(not 0 <= k < FOLDS for k in folds):
        ap.error(f"--folds: fold numbers from 0 to {FOLDS - 1}")
    models = [(alg, json.loads(p)) for alg, p in a.model] if a.model else DEFAULT_MODELS
    rows = walks(a.data_dir)
    print(f"{len(rows)} walks, {sum(map(len, rows))} scans; folds {folds}")
    print("| model | scans | mean m | p50 m | p90 m | per fold (mean m) | chosen | fit + locate s |")
    print("|---|---|---|---|---|---|---|---|")
    for alg, params in models:
        t0 = time.perf_counter()
        per_fold = [fold_errors(rows, k, alg, params) for k in folds]
        e = np.concatenate([errs for errs, _ in per_fold])
        print(f"| {alg} {json.dumps(params) if params else ''} | {len(e)} | {e.mean():.2f} | {np.median(e):.2f} | "
              f"{np.percentile(e, 90):.2f} | {', '.join(f'{errs.mean():.2f}' for errs, _ in per_fold)} | "
              f"{'; '.join(json.dumps(c) for _, c in per_fold if c)} | {time.perf_counter() - t0:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
