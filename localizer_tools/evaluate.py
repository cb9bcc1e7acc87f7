"""Train fingerprint algorithms on a data set and print held-out metrics.

    python -m localizer_tools.evaluate TRAIN [TEST] [--format auto|csv|ujiindoorloc|ujible|json|msft]
        [--split user|phone|power|random] [--algorithms wknn,knn,...] [--kinds wifi,ble]
        [--use-heading] [--missing powed|floor|exponential] [--params JSON]

Without TEST, TRAIN is split: whole users or phones held out (about --test-fraction
of the rows), a UJI BLE beacon power (``power``), or a random share of rows. Any data
set the upload accepts (survey CSV, UJIIndoorLoc CSV, JSON rows) and the shared UJI
BLE and MSFT directories are read (``--format auto`` tells them apart); a data set
that cannot be read or split prints one ``error:`` line and exits 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace

from server.estimation.fingerprint.features import MISSING_MODES
from server.estimation.fingerprint.loaders import FORMATS, detect_format, load, read_uji_ble_beacons
from server.estimation.fingerprint.metrics import evaluate, holdout_split
from server.estimation.fingerprint.registry import ALGORITHMS, make_model

COLUMNS = [
    ("algorithm", "{:<14}"), ("mean_error_m", "{:>7.2f}"), ("p50_error_m", "{:>7.2f}"), ("p90_error_m", "{:>7.2f}"),
    ("mapping_rate", "{:>8.3f}"), ("floor_hit_rate", "{:>7.3f}"), ("building_hit_rate", "{:>7.3f}"),
    ("fit_time_s", "{:>8.2f}"), ("us_per_query", "{:>8.0f}"), ("single_query_us", "{:>9.0f}"),
]
HEADS = ["algorithm", "mean m", "p50 m", "p90 m", "mapping", "floor", "bldg", "fit s", "µs/q", "1-query µs"]


def format_table(rows: list[dict], markdown: bool = False) -> str:
    if markdown:
        out = ["| " + " | ".join(HEADS) + " |", "|" + "---|" * len(HEADS)]
        for r in rows:
            out.append("| " + " | ".join(f.format(r[k]).strip() for k, f in COLUMNS) + " |")
        return "\n".join(out)
    widths = [len(f.format(0 if k != "algorithm" else "")) for k, f in COLUMNS]
    out = ["  ".join(h.rjust(w) if i else h.ljust(w) for i, (h, w) in enumerate(zip(HEADS, widths, strict=True)))]
    for r in rows:
        out.append("  ".join(f.format(r[k]) for k, f in COLUMNS))
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localizer_tools.evaluate", description=(__doc__ or "").splitlines()[0])
    ap.add_argument("train")
    ap.add_argument("test", nargs="?")
    ap.add_argument("--format", default="auto", choices=list(FORMATS))
    ap.add_argument("--split", default="user", choices=["user", "phone", "power", "random"])
    ap.add_argument("--test-fraction", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--algorithms", default="wknn,nbc,knn,svm,kde,tkbe,propagation")
    ap.add_argument("--kinds", default=None, help="comma-separated: wifi,ble (default all)")
    ap.add_argument("--use-heading", action="store_true")
    ap.add_argument("--missing", default=None, choices=list(MISSING_MODES))
    ap.add_argument("--params", default="{}", help='JSON {"knn": {"k": 5}, ...} or {"k": 5} for all')
    ap.add_argument("--with-beacons", action="store_true",
                    help="ujible: give the propagation model the beacon positions from dep/lib.csv")
    ap.add_argument("--shift-db", type=float, default=0.0,
                    help="add this many dB to every reading of the test rows (a phone, or a beacon power, "
                         "reading louder or quieter than the survey's)")
    ap.add_argument("--markdown", action="store_true")
    a = ap.parse_args(argv)
    try:
        return _run(a)
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def _run(a) -> int:
    if not 0.0 < a.test_fraction < 1.0:  # (NaN fails too)
        raise ValueError(f"--test-fraction must lie strictly between 0 and 1, not {a.test_fraction}")
    fs = load(a.train, a.format)
    if not len(fs):
        raise ValueError(f"{a.train}: no fingerprint hears any transmitter")
    if a.test:
        train, test, desc = fs, load(a.test, a.format), f"test file {a.test}"
    else:
        train, test, desc = holdout_split(fs, a.split, a.test_fraction, a.seed)
    if not len(test):
        raise ValueError(f"the {a.split} split held out no rows: nothing to evaluate on")
    if not math.isfinite(a.shift_db):
        raise ValueError(f"--shift-db must be a finite number of dB, not {a.shift_db}")
    if a.shift_db:
        test = replace(test, rss=test.rss + a.shift_db)
        desc += f", readings shifted by {a.shift_db:+g} dB"
    cover = set(train.rp_keys())
    coverage = sum(k in cover for k in test.rp_keys()) / max(len(test), 1)
    print(f"# {a.train} ({a.format}): {len(fs)} rows, skipped {fs.meta.get('skipped', 0)}; "
          f"train {len(train)}, test {len(test)} ({desc}); "
          f"test rows whose reference point is in train: {coverage:.3f}", flush=True)
    kinds = a.kinds.split(",") if a.kinds else None
    params = json.loads(a.params)
    rows = []
    for name in [s.strip() for s in a.algorithms.split(",") if s.strip()]:
        if name not in ALGORITHMS:
            print(f"unknown algorithm {name}", file=sys.stderr)
            return 2
        p = dict(params.get(name, {})) if any(k in ALGORITHMS for k in params) else dict(params)
        if a.missing:
            p["missing"] = a.missing
        if name == "propagation" and a.with_beacons and detect_format(a.train) == "ujible":
            p["transmitters"] = read_uji_ble_beacons(a.train)
        model = make_model(name, p, use_heading=a.use_heading, kinds=kinds).fit(train)
        m = evaluate(model, test).as_dict()
        rows.append(m)
        print(format_table([m]).splitlines()[1], file=sys.stderr, flush=True)
    print(format_table(rows, markdown=a.markdown))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
