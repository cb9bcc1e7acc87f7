"""What tells a good fingerprint fix from a bad one (MSFT site 1 F1): the rank correlation of each
fix's error with what the model knows when it answers.

    python benchmarks/fix_error_predictors.py [DATA_DIR] [--folds 4] [--algorithm knn]

Per fold (walk i is tested in fold i % 4, as in ``client_sim msft``) a model is fitted on the other
walks and every scan of the fold's test walks is located. Printed per pair of folds (0–1 choose,
2–3 report, as every MSFT choice here): Spearman's ρ between the fix error (m) and the model's raw
σ (√(tr C / 2), before any calibration), the scan's coverage distance (signal-space distance to the
nearest fingerprint, KNN family only), the transmitters the scan heard and those the map knows, and
the best reference point's posterior probability. A served covariance that tracks the error lets a
tracker trust a good fix more than a bad one; one that does not (the calibration's floor dominates
on these maps) makes every fix count the same. Chooses nothing; a diagnostic.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.msft_fingerprint import walk_rows  # noqa: E402
from benchmarks.shared_data import SHARED_DATA  # noqa: E402
from client_sim.errors import number  # noqa: E402
from server.estimation.fingerprint import FingerprintSet, make_model  # noqa: E402

FEATURES = ("raw σ", "coverage distance", "heard", "known", "top posterior")


def fold_features(rows: list[list[dict]], fold: int, folds: int, algorithm: str) -> tuple[np.ndarray, np.ndarray]:
    """(errors (n,), features (n, len(FEATURES))) of the fold's test scans that hear a known transmitter."""
    model = make_model(algorithm, {}, kinds=["wifi"]).fit(
        FingerprintSet.from_rows([r for i in range(len(rows)) if i % folds != fold for r in rows[i]]))
    known = set(model.tx_ids_)
    scans = [r for i in range(len(rows)) if i % folds == fold for r in rows[i] if known & set(r["rss"])]
    M = model.scan_matrix([r["rss"] for r in scans])
    pred = model.predict(M, calibrated=False)
    coverage = model.coverage(M)[0] if hasattr(model, "coverage") else np.full(len(scans), np.nan)
    err = np.hypot(pred.x - [r["x"] for r in scans], pred.y - [r["y"] for r in scans])
    feats = np.column_stack((
        np.sqrt(np.trace(pred.covariance, axis1=1, axis2=2) / 2.0), coverage,
        [len(r["rss"]) for r in scans], [len(known & set(r["rss"])) for r in scans], pred.top_p[:, 0],
    ))
    return err, feats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data_dir", nargs="?", default=str(SHARED_DATA / "msft_site1_f1"))
    parser.add_argument("--folds", type=number(int, 2), default=4)
    parser.add_argument("--algorithm", default="knn")
    parser.add_argument("--max-age", type=number(float, 0, above=True), default=3.0,
                        help="WiFi entries older than this (s) are dropped")
    args = parser.parse_args()
    _, rows = walk_rows(args.data_dir, args.max_age)
    per_fold = [fold_features(rows, f, args.folds, args.algorithm) for f in range(args.folds)]
    half = args.folds // 2
    groups = {f"folds 0–{half - 1}": per_fold[:half], f"folds {half}–{args.folds - 1}": per_fold[half:]}
    print(f"Spearman ρ of a {args.algorithm} fix's error with (MSFT, {args.folds} folds):")
    print("| folds | fixes | median error m | " + " | ".join(FEATURES) + " |")
    print("|---" * (3 + len(FEATURES)) + "|")
    for name, parts in groups.items():
        err = np.concatenate([e for e, _ in parts])
        feats = np.concatenate([f for _, f in parts])
        rhos = [spearmanr(feats[:, j], err, nan_policy="omit").statistic for j in range(len(FEATURES))]
        print(f"| {name} | {len(err)} | {np.median(err):.1f} | " + " | ".join(f"{r:+.2f}" for r in rhos) + " |")


if __name__ == "__main__":
    main()
