"""The floor classifier fitted on a bounded sample: how many fingerprints it needs.

The RBF SVC that picks the floor for knn, kde, nbc, tkbe and propagation (alone:
``floor_classifier="svc"``, measured here; or after `FloorKNN`'s building in the default
"knn-svc") fits in ≈ n² and stores ≈ n support vectors; fitted on a stratified sample of at most
``floor_classifier_rows`` fingerprints, both are bounded. UJIIndoorLoc users are split
as in benchmarks/fingerprint_choice.py: the cap is CHOSEN on the CHOOSE users (trained
on everyone outside CHOOSE ∪ REPORT), then REPORTED once on the REPORT users (trained on
everyone outside REPORT) for the chosen cap and for no cap.

    .venv/bin/python -m benchmarks.floor_classifier_scale [--data ../shared/data/ujiindoorloc]
        [--caps 1000,2000,4000,8000,0] [--stage choose|report|both]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.fingerprint_choice import CHOOSE, REPORT, user_ids
from benchmarks.shared_data import UJIINDOORLOC
from server.estimation.fingerprint.base import FLOOR_CLASSIFIER_ROWS
from server.estimation.fingerprint.loaders import read_ujiindoorloc
from server.estimation.fingerprint.registry import make_model


def run(train, test, cap: int) -> str:
    t0 = time.perf_counter()
    model = make_model("knn", {"floor_classifier": "svc", "floor_classifier_rows": cap or len(train)}).fit(train)
    fit_s = time.perf_counter() - t0
    pred = model.predict(test.aligned_rss(model.tx_ids_))
    floor = float(np.mean((pred.floor == test.floor) & (pred.building == test.building)))
    building = float(np.mean(pred.building == test.building))
    sv = int(model.floor_clf_.support_vectors_.shape[0])
    return (f"| {cap or 'all'} | {100 * floor:.1f} % | {100 * building:.2f} % | "
            f"{np.mean(np.hypot(pred.x - test.x, pred.y - test.y)):.2f} | {fit_s:.1f} | {sv:,} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=UJIINDOORLOC,
                    help="folder with trainingData.csv (default %(default)s)")
    ap.add_argument("--caps", default="1000,2000,4000,8000,0", help="caps tried on CHOOSE (0 = all; default %(default)s)")
    ap.add_argument("--stage", default="both", choices=["choose", "report", "both"], help="default %(default)s")
    a = ap.parse_args(argv)
    fs = read_ujiindoorloc(str(a.data / "trainingData.csv"))
    user = user_ids(fs)
    head = ("| cap | floor hit (building and floor) | building hit | knn mean m | fit s | support vectors |\n"
            "|---|---|---|---|---|---|")
    if a.stage in ("choose", "both"):
        train, test = fs.subset(~np.isin(user, list(CHOOSE | REPORT))), fs.subset(np.isin(user, list(CHOOSE)))
        print(f"## choose: train {len(train)} (users outside {sorted(CHOOSE | REPORT)}), test {len(test)} "
              f"(users {sorted(CHOOSE)})\n{head}", flush=True)
        for cap in (int(c) for c in a.caps.split(",")):
            print(run(train, test, cap), flush=True)
    if a.stage in ("report", "both"):
        train, test = fs.subset(~np.isin(user, list(REPORT))), fs.subset(np.isin(user, list(REPORT)))
        print(f"## report: train {len(train)} (users outside {sorted(REPORT)}), test {len(test)} "
              f"(users {sorted(REPORT)})\n{head}", flush=True)
        for cap in (FLOOR_CLASSIFIER_ROWS, 0):
            print(run(train, test, cap), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
