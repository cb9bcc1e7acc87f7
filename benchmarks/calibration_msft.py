"""How steady the training step's covariance calibration is, and how it transfers to new walks (MSFT site 1 F1).

    python benchmarks/calibration_msft.py [DATA_DIR] [--cov-floor 8] [--bootstrap 100]

Per fold (walk i is tested in fold i % 4, as in ``client_sim msft``): the map walks' rows
(``device`` = the walk) go through the training step's held-out stage (`held_out_stage`: every walk
held out once in 5 folds) and `fit_calibration` is fitted on those residuals,
as the server does. Printed: the fitted (scale, floor), the served σ per axis at the map's
median and 90th-percentile raw σ (where the fixes' covariances lie), the 10th–90th
percentiles of that served σ over bootstrap resamples of the residuals (how much the fit
moves with the sample), and on the fold's *test* walks (a model of all the map walks) the
calibrated NIS clipped mean (2 when calibrated) and median (χ²₂: 1.39), beside the
calibration fitted on the test walks themselves (an oracle no server has).
``--cov-floor`` is the model's ``cov_floor_m`` (``client_sim msft`` sets 7.3–8.9 m from a
map cross-validation). Chooses nothing; a diagnostic.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.msft_fingerprint import walk_rows  # noqa: E402
from benchmarks.shared_data import SHARED_DATA  # noqa: E402
from server.estimation.fingerprint import FingerprintSet, held_out_stage, make_model  # noqa: E402
from server.estimation.fingerprint.calibration import (  # noqa: E402
    CovarianceCalibration,
    clipped_mean,
    fit_calibration,
    nis,
)


def served_sigma(cal: CovarianceCalibration, raw_sigma: float) -> float:
    """Per-axis σ served for a raw isotropic σ (m)."""
    return float(np.sqrt(cal.scale * raw_sigma**2 + cal.floor_m**2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_dir", nargs="?", default=str(SHARED_DATA / "msft_site1_f1"))
    ap.add_argument("--cov-floor", type=float, default=8.0, help="the knn's cov_floor_m (m)")
    ap.add_argument("--bootstrap", type=int, default=100, help="resamples of the held-out residuals")
    ap.add_argument("--folds", type=int, default=4)
    a = ap.parse_args()

    rows = walk_rows(a.data_dir, 3.0)[1]
    n = len(rows)

    def factory():
        return make_model("knn", {"cov_floor_m": a.cov_floor}, kinds=["wifi"])

    print(f"{n} walks, knn cov_floor_m {a.cov_floor:g}, {a.bootstrap} bootstrap resamples")
    print("| fold | held-out | scale, floor m | raw σ p50 / p90 | served σ there | bootstrap p10–p90 | "
          "test NIS clipped mean / median | oracle scale, floor; served σ |")
    print("|---|---|---|---|---|---|---|---|")
    for k in range(a.folds):
        fs = FingerprintSet.from_rows([r for j in range(n) if j % a.folds != k for r in rows[j]])
        stage = held_out_stage(factory, fs, "device", 0.2, 0)
        held = stage.pooled
        assert held is not None
        cal = fit_calibration(held.residuals, held.covariances)
        raw = np.sqrt(0.5 * (held.covariances[:, 0, 0] + held.covariances[:, 1, 1]))
        spots = np.percentile(raw, [50, 90])
        rng = np.random.default_rng(k)
        boot = np.array([[served_sigma(fit_calibration(held.residuals[i], held.covariances[i]), s) for s in spots]
                         for i in (rng.integers(0, len(raw), len(raw)) for _ in range(a.bootstrap))])
        full = factory()
        full.reuse_choices(stage.validated)
        full.fit(fs)
        test = FingerprintSet.from_rows([r for j in range(n) if j % a.folds == k for r in rows[j]])
        test = test.select_kinds(["wifi"]).drop_empty()
        pred = full.predict(test.aligned_rss(full.tx_ids_), None, calibrated=False)
        rt = pred.xy - np.column_stack([test.x, test.y])
        q = nis(rt, cal.apply(pred.covariance))
        oracle = fit_calibration(rt, pred.covariance)
        lo, hi = np.percentile(boot, [10, 90], axis=0)
        print(f"| {k} | {len(raw)} | {cal.scale:.3g}, {cal.floor_m:g} | {spots[0]:.1f} / {spots[1]:.1f} | "
              f"{served_sigma(cal, spots[0]):.1f} / {served_sigma(cal, spots[1]):.1f} | "
              f"{lo[0]:.1f}–{hi[0]:.1f} / {lo[1]:.1f}–{hi[1]:.1f} | {clipped_mean(q):.2f} / {np.median(q):.2f} | "
              f"{oracle.scale:.3g}, {oracle.floor_m:g}; {served_sigma(oracle, spots[0]):.1f} / "
              f"{served_sigma(oracle, spots[1]):.1f} |", flush=True)


if __name__ == "__main__":
    main()
