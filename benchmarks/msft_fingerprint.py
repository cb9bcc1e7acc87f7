"""Fingerprinting alone on the MSFT site-1 F1 walks, in-process: how much of its error is the map's reach.

    python benchmarks/msft_fingerprint.py [DATA_DIR] [--algorithm knn] [--max-age 3] [--loo] [--per-walk]

The same rows as ``client_sim msft`` (each walk's WiFi scans, stale entries dropped at
``--max-age`` s, placed at the waypoint-interpolated position; ``device`` = the walk) and the
same folds (walk i is tested in fold i % 4, located by a model fitted on the other walks), but
fitted and located in this process with the estimation layer (no server: seconds instead of a
minute). ``client_sim msft``'s own fingerprint-only figure is the same model through HTTP (its
map model also gets the cross-validated fix-noise floor, which moves covariances, not
positions). ``--loo`` adds every walk left out once from a map of all the others (42 walks
instead of ~32): the difference is how much a denser crowd map would buy.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.shared_data import SHARED_DATA  # noqa: E402
from client_sim.msft import read_walk, survey_rows, wifi_scans  # noqa: E402
from client_sim.msft_eval import walk_files  # noqa: E402
from server.estimation.fingerprint import FingerprintSet, UnknownTransmittersError, make_model  # noqa: E402


def walk_rows(data_dir: str | Path, max_age_s: float) -> tuple[list, list[list[dict]]]:
    """The walks under ``data_dir`` and each one's survey rows as ``client_sim msft`` uploads them
    (WiFi entries older than ``max_age_s`` dropped, placed on the waypoints, ``device`` = the walk);
    exits naming the folder when it holds no walk."""
    files = walk_files(Path(data_dir))
    if not files:
        raise SystemExit(f"error: no walk files under {data_dir}")
    walks = [read_walk(f) for f in files]
    return walks, [survey_rows(w, wifi_scans(w, max_age_s), device=f"msft-{w.name}") for w in walks]


def errors_by_walk(rows: list[list[dict]], maps_for, algorithm: str) -> list[np.ndarray]:
    """Each walk's fix errors (m) from a model fitted on ``maps_for(i)``'s walks; one model per
    distinct map (a fold's walks share theirs)."""
    out: list[np.ndarray] = [np.zeros(0)] * len(rows)
    by_map: dict[tuple[int, ...], list[int]] = {}
    for i in range(len(rows)):
        by_map.setdefault(tuple(maps_for(i)), []).append(i)
    for map_idx, tests in by_map.items():
        model = make_model(algorithm, {}, kinds=["wifi"]).fit(FingerprintSet.from_rows([r for j in map_idx for r in rows[j]]))
        for i in tests:
            errs = []
            for r in rows[i]:
                try:
                    fix = model.locate(r["rss"], heading_deg=None)
                except UnknownTransmittersError:  # nothing in this scan is in the map
                    continue
                errs.append(float(np.hypot(fix.x - r["x"], fix.y - r["y"])))
            out[i] = np.asarray(errs)
    return out


def summary(name: str, per_walk: list[np.ndarray]) -> str:
    e = np.concatenate(per_walk)
    return (f"{name:<24} fixes {len(e):4d}  mean {e.mean():6.2f}  p50 {np.median(e):6.2f}  "
            f"p90 {np.percentile(e, 90):6.2f} m")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_dir", nargs="?", default=str(SHARED_DATA / "msft_site1_f1"))
    ap.add_argument("--algorithm", default="knn")
    ap.add_argument("--max-age", type=float, default=3.0, help="drop WiFi entries last seen longer ago (s)")
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--loo", action="store_true", help="also leave each walk out of a map of all the others")
    ap.add_argument("--per-walk", action="store_true", help="print each walk's mean error")
    a = ap.parse_args()

    walks, rows = walk_rows(a.data_dir, a.max_age)
    n = len(walks)
    folds = errors_by_walk(rows, lambda i: [j for j in range(n) if j % a.folds != i % a.folds], a.algorithm)
    print(f"{n} walks, {a.algorithm}, WiFi max age {a.max_age:g} s")
    print(summary(f"{a.folds} folds", folds))
    loo = errors_by_walk(rows, lambda i: [j for j in range(n) if j != i], a.algorithm) if a.loo else None
    if loo is not None:
        print(summary("each walk left out", loo))
    if a.per_walk:
        for i, w in enumerate(walks):
            extra = f"  left out {loo[i].mean():6.2f}" if loo is not None and len(loo[i]) else ""
            mean = f"{folds[i].mean():6.2f}" if len(folds[i]) else "     —"
            print(f"{i:3d} {w.name}  fixes {len(folds[i]):3d}  {a.folds} folds {mean}{extra}")


if __name__ == "__main__":
    main()
