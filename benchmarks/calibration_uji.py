"""Held-out NIS of fixes on UJIIndoorLoc before and after the training step's covariance calibration.

Users split as in benchmarks/fingerprint_choice.py: models are trained on every user
outside CHOOSE ∪ REPORT; the calibration (calibration.py) is fitted on the residuals of
the CHOOSE users' scans; the NIS is reported on the REPORT users' scans, which neither
the fit nor the calibration saw. A calibrated 2-D fix has mean NIS 2 (clipped at χ²₂'s
99.9 % quantile: 2.00) and median 1.39.

    .venv/bin/python -m benchmarks.calibration_uji [--data ../shared/data/ujiindoorloc] [--sample N]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.fingerprint_choice import CHOOSE, REPORT, user_ids
from benchmarks.shared_data import UJIINDOORLOC
from server.estimation.fingerprint.calibration import IDENTITY, clipped_mean, fit_calibration, nis
from server.estimation.fingerprint.loaders import read_ujiindoorloc
from server.estimation.fingerprint.registry import make_model


def _sample(fs, n: int):
    if not n or n >= len(fs):
        return fs
    return fs.subset(np.sort(np.random.default_rng(0).choice(len(fs), n, replace=False)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(UJIINDOORLOC), help="folder with trainingData.csv (default %(default)s)")
    ap.add_argument("--sample", type=int, default=2000, help="scans per held-out user set (0 = all; default %(default)s)")
    ap.add_argument("--algorithms", default="knn,wknn", help="comma-separated (default %(default)s)")
    a = ap.parse_args(argv)
    fs = read_ujiindoorloc(str(Path(a.data) / "trainingData.csv"))
    user = user_ids(fs)
    train = fs.subset(~np.isin(user, list(CHOOSE | REPORT)))
    choose = _sample(fs.subset(np.isin(user, list(CHOOSE))), a.sample)
    report = _sample(fs.subset(np.isin(user, list(REPORT))), a.sample)
    print(f"train {len(train)} scans (users outside {sorted(CHOOSE | REPORT)}); calibration chosen on {len(choose)} "
          f"scans of users {sorted(CHOOSE)}; NIS reported on {len(report)} scans of users {sorted(REPORT)}")
    print("| model | covariance | calibration (scale, floor m) | NIS mean (clipped) | NIS median |")
    print("|---|---|---|---|---|")
    for algo in a.algorithms.split(","):
        model = make_model(algo, {}).fit(train)

        def residuals(test, model=model):
            pred = model.predict(test.aligned_rss(model.tx_ids_), calibrated=False)
            return pred.xy - np.column_stack([test.x, test.y]), pred.covariance

        r_choose, c_choose = residuals(choose)
        r_report, c_report = residuals(report)
        rows = [("raw (uncalibrated)", IDENTITY)]
        if model.calibration_ != IDENTITY:
            rows.append(("the model's own (internal CV on the training users)", model.calibration_))
        rows.append(("training step's, fitted on CHOOSE users", fit_calibration(r_choose, c_choose)))
        for name, cal in rows:
            v = nis(r_report, cal.apply(c_report))
            print(f"| {algo} | {name} | {cal.scale:.3g}, {cal.floor_m:g} | {clipped_mean(v):.2f} | {np.median(v):.2f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
