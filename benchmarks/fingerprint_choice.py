"""How the default fingerprint model was chosen on UJIIndoorLoc, honestly.

Users of trainingData.csv are split three ways (each of these users carried his own
phone, so a held-out user is also a held-out phone):

- CHOOSE users {2, 6, 7, 14} (phones 23, 19, 6, 7): candidates are trained on every
  user outside CHOOSE ∪ REPORT and compared on CHOOSE; the winner is picked here.
- REPORT users {4, 8, 10, 13, 17, 18} (phones 18, 1, 8, 17, 22, 10): never looked at
  while choosing; the picked configurations and the baseline are trained on every
  user outside REPORT and measured once on REPORT.

Baseline: a bare scikit-learn brute-force KNN, k = 3, −110 dBm for not heard (raw
dBm features), floor and building by the same 3 neighbours (majority).

    .venv/bin/python -m benchmarks.fingerprint_choice [--stage choose|report|both] [--sample N] [--shift dB]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np

from benchmarks.shared_data import UJIINDOORLOC
from server.estimation.fingerprint.loaders import read_ujiindoorloc
from server.estimation.fingerprint.registry import make_model

DATA = UJIINDOORLOC / "trainingData.csv"
CHOOSE = {2, 6, 7, 14}
REPORT = {4, 8, 10, 13, 17, 18}


def user_ids(fs) -> np.ndarray:
    """Each row's USERID: the choosing (CHOOSE) and reporting (REPORT) splits go by user."""
    if fs.user is None:
        raise SystemExit("these rows carry no USERID: the choosing/reporting split needs UJIIndoorLoc's")
    return fs.user.astype(int)

CANDIDATES: dict[str, tuple[str, dict]] = {
    "knn (k=3, 1/d weights: the default)": ("knn", {}),
    "knn, uniform weights": ("knn", {"weights": "uniform"}),
    "knn, no offset estimate": ("knn", {"offset_estimate": False}),
    "knn, offset estimate from >= 3 transmitters": ("knn", {"offset_min_tx": 3}),
    "knn, offset estimate from >= 5 transmitters": ("knn", {"offset_min_tx": 5}),
    "knn, offset estimate from >= 8 transmitters": ("knn", {"offset_min_tx": 8}),
    "knn, offset estimate from >= 12 transmitters": ("knn", {"offset_min_tx": 12}),
    "knn, offset estimate from >= 16 transmitters": ("knn", {"offset_min_tx": 16}),
    "wknn powed sorensen": ("wknn", {"missing": "powed"}),
    "wknn powed sorensen, no offset estimate": ("wknn", {"missing": "powed", "offset_estimate": False}),
    "wknn powed sorensen, offset search ±6 dB": ("wknn", {"missing": "powed", "offset_estimate": False,
                                                          "offset_search_db": 6.0}),
    "wknn powed sorensen, no cleaning": ("wknn", {"missing": "powed", "dedupe": False, "min_tx_rows": 0}),
    "wknn powed sorensen, SVC floor": ("wknn", {"missing": "powed", "floor_classifier": "svc"}),
    "wknn powed euclidean": ("wknn", {"missing": "powed", "distance": "euclidean"}),
    "wknn exponential sorensen (chosen: the default)": ("wknn", {}),
    "wknn exponential sorensen, no offset estimate": ("wknn", {"offset_estimate": False}),
    "wknn exponential sorensen, offset estimate from >= 8 transmitters": ("wknn", {"offset_min_tx": 8}),
    "wknn positive sorensen": ("wknn", {"missing": "floor"}),
    "wknn positive euclidean": ("wknn", {"missing": "floor", "distance": "euclidean"}),
}


def baseline(train, test) -> dict:
    from sklearn.neighbors import KNeighborsClassifier, KNeighborsRegressor

    t0 = time.perf_counter()
    Xtr = np.nan_to_num(train.rss, nan=-110.0)
    Xte = np.nan_to_num(test.aligned_rss(train.tx_ids), nan=-110.0)
    reg = KNeighborsRegressor(n_neighbors=3, algorithm="brute").fit(Xtr, np.column_stack([train.x, train.y]))
    fl = KNeighborsClassifier(n_neighbors=3, algorithm="brute").fit(Xtr, train.floor)
    bl = KNeighborsClassifier(n_neighbors=3, algorithm="brute").fit(Xtr, train.building)
    fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    xy = reg.predict(Xte)
    f, b = fl.predict(Xte), bl.predict(Xte)
    q = (time.perf_counter() - t0) / len(test)
    return _row("sklearn brute KNN k=3, −110 dBm", xy, f, b, test, fit, q)


def _row(name, xy, floor, building, test, fit_s, q_s) -> dict:
    err = np.hypot(xy[:, 0] - test.x, xy[:, 1] - test.y)
    return {"model": name, "mean": float(err.mean()), "p50": float(np.median(err)),
            "p90": float(np.percentile(err, 90)), "floor": float(np.mean(floor == test.floor)),
            "building": float(np.mean(building == test.building)), "fit_s": fit_s, "ms_per_q": 1e3 * q_s}


def run_model(name, algo, params, train, test) -> dict:
    model = make_model(algo, params).fit(train)
    t0 = time.perf_counter()
    pred = model.predict(test.aligned_rss(model.tx_ids_))
    q = (time.perf_counter() - t0) / len(test)
    row = _row(name, pred.xy, pred.floor, pred.building, test, model.fit_time_s_, q)
    r = pred.xy - np.column_stack([test.x, test.y])
    nis = np.einsum("ni,nij,nj->n", r, np.linalg.inv(pred.covariance), r)
    row["nis_mean"], row["nis_median"] = float(nis.mean()), float(np.median(nis))
    if hasattr(model, "k_"):
        row["model"] += f" (k={model.k_})"
    return row


def table(rows) -> str:
    out = ["| model | mean m | p50 m | p90 m | floor | building | NIS p50 | fit s | ms/query |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['model']} | {r['mean']:.2f} | {r['p50']:.2f} | {r['p90']:.2f} | {100 * r['floor']:.1f} % "
                   f"| {100 * r['building']:.1f} % | {r.get('nis_median', float('nan')):.2f} | {r['fit_s']:.1f} "
                   f"| {r['ms_per_q']:.2f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--stage", default="choose", choices=["choose", "report", "both"])
    ap.add_argument("--sample", type=int, default=0, help="subsample test rows (0 = all)")
    ap.add_argument("--shift", type=float, default=0.0,
                    help="add this many dB to every test reading (a phone with an RSS offset)")
    ap.add_argument("--only", default="", help="semicolon-separated substrings of candidate names")
    ap.add_argument("--report-models", help="semicolon-separated candidate names measured on REPORT",
                    default="wknn exponential sorensen (chosen: the default);wknn exponential sorensen, no offset estimate;"
                            "wknn positive sorensen;wknn powed sorensen;knn (k=3, 1/d weights: the default)")
    a = ap.parse_args(argv)
    fs = read_ujiindoorloc(DATA)
    user = user_ids(fs)
    stages = ["choose", "report"] if a.stage == "both" else [a.stage]
    for stage in stages:
        held = CHOOSE if stage == "choose" else REPORT
        out_train = CHOOSE | REPORT if stage == "choose" else REPORT
        train = fs.subset(~np.isin(user, list(out_train)))
        test = fs.subset(np.isin(user, list(held)))
        if a.sample and a.sample < len(test):
            test = test.subset(np.sort(np.random.default_rng(0).choice(len(test), a.sample, replace=False)))
        if a.shift:
            test = replace(test, rss=test.rss + a.shift)
        print(f"## {stage}: train {len(train)} rows (users outside {sorted(out_train)}), "
              f"test {len(test)} rows (users {sorted(held)}), readings shifted by {a.shift:+g} dB", flush=True)
        rows = [baseline(train, test)]
        print(json.dumps(rows[-1]), flush=True)
        names = list(CANDIDATES) if stage == "choose" else [n.strip() for n in a.report_models.split(";")]
        if a.only:
            names = [n for n in names if any(o in n for o in a.only.split(";"))]
        for name in names:
            algo, params = CANDIDATES[name]
            rows.append(run_model(name, algo, params, train, test))
            print(json.dumps(rows[-1]), flush=True)
        print(table(rows), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
