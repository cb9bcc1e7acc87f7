"""``python -m client_sim <command>``: step counting, survey / track / crowd clients, reports.

Server URL and keys come from options or the environment: ``LOCALIZER_URL``,
``LOCALIZER_ADMIN_KEY`` and ``LOCALIZER_DEVICE_KEY`` (both fall back to
``LOCALIZER_API_KEY``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
from pathlib import Path

from tqdm import tqdm


def _env(*names: str, default: str | None = None) -> str | None:
    for n in names:
        if os.environ.get(n):
            return os.environ[n]
    return default


def _server_args(p: argparse.ArgumentParser, admin: bool, device: bool) -> None:
    p.add_argument("--url", default=_env("LOCALIZER_URL", default="http://127.0.0.1:8000"),
                   help="server base URL (env LOCALIZER_URL)")
    if admin:
        p.add_argument("--admin-key", default=_env("LOCALIZER_ADMIN_KEY", "LOCALIZER_API_KEY"),
                       help="admin key (env LOCALIZER_ADMIN_KEY or LOCALIZER_API_KEY)")
    if device:
        p.add_argument("--device-key", default=_env("LOCALIZER_DEVICE_KEY", "LOCALIZER_API_KEY"),
                       help="device key (env LOCALIZER_DEVICE_KEY or LOCALIZER_API_KEY)")


def _write(path: str | None, data: dict) -> None:
    text = json.dumps(data, indent=1)
    if path:
        Path(path).write_text(text)
        print(f"wrote {path}", file=sys.stderr)
    else:
        print(text)


def cmd_steps(a) -> None:
    from .oxford import count_steps

    for f in a.files:
        print(count_steps(f) if len(a.files) == 1 else f"{f}\t{count_steps(f)}")


def cmd_eval_steps(a) -> None:
    from .oxford import evaluate, summarise

    results = evaluate(a.data_dir, progress=lambda rows: tqdm(rows, desc="traces"))
    table = summarise(results)
    print("| position | traces | mean abs count error (%) | max (%) |\n|---|---|---|---|")
    for pos, s in table.items():
        print(f"| {pos} | {s['traces']} | {s['mean_error_pct']:.2f} | {s['max_error_pct']:.2f} |")
    if a.json:
        _write(a.json, {"table": table, "traces": [r.__dict__ | {"error_pct": r.error_pct} for r in results]})


def cmd_scenario(a) -> None:
    from .report import plot_scenario
    from .world import get_world

    world = get_world(a.scenario)
    if a.json:
        world.to_json(a.json)
    if a.png:
        plot_scenario(world, a.png, a.seed)
    if not (a.json or a.png):
        print(json.dumps(world.site_payload(), indent=1))


def cmd_survey(a) -> None:
    from .runs import run_survey

    res = asyncio.run(run_survey(a.url, a.admin_key, a.scenario, scans_per_heading=a.scans, seed=a.seed,
                                 train=a.train, site_name=a.site_name, progress=True))
    _write(a.out, res)


def cmd_track(a) -> None:
    from .runs import run_track

    res = asyncio.run(run_track(a.url, a.device_key, a.scenario, a.site_id, phones=a.phones,
                                filters=a.filters.split(","), seed=a.seed, interval_s=a.interval, speed=a.speed,
                                wifi_hz=a.wifi_hz, ble_hz=a.ble_hz, initial=not a.no_initial, retries=a.retries,
                                progress=True))
    _write(a.out, res)


def cmd_crowd(a) -> None:
    from .runs import run_crowd

    res = asyncio.run(run_crowd(a.url, a.admin_key, a.device_key, a.scenario, rounds=a.rounds, phones=a.phones,
                                filter=a.filter, seed=a.seed, train=a.train or None, probes=a.probes,
                                site_id=a.site_id, interval_s=a.interval, progress=True))
    _write(a.out, res)


def cmd_report(a) -> None:
    from .report import markdown_table, write_report

    print(markdown_table(write_report(a.results, a.out)), end="")


def cmd_demo(a) -> None:
    from .demo import main as demo

    sys.exit(demo(a))


def cmd_msft(a) -> None:
    from .msft_eval import main as msft

    sys.exit(msft(a))


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="client_sim", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("steps", help="count steps in accelerometer CSV file(s) (time_ns, [acc,] x, y, z)")
    p.add_argument("files", nargs="+")
    p.set_defaults(func=cmd_steps)

    p = sub.add_parser("eval-steps", help="step-count error per phone position on the Oxford set")
    p.add_argument("data_dir", help="directory with stats.csv and data/<trace>/accelerometer.csv")
    p.add_argument("--json", help="also write per-trace results here")
    p.set_defaults(func=cmd_eval_steps)

    p = sub.add_parser("scenario", help="export a scenario as JSON and/or plot its floor plan with a walk")
    p.add_argument("scenario", help="open_room | corridor_loop | multi_floor | path/to/world.json")
    p.add_argument("--json")
    p.add_argument("--png")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_scenario)

    p = sub.add_parser("survey", help="create the scenario's site and upload a survey")
    _server_args(p, admin=True, device=False)
    p.add_argument("--scenario", default="open_room")
    p.add_argument("--scans", type=int, default=5, help="scans per heading per reference point")
    p.add_argument("--train", help="request a model with this algorithm (nbc, knn, svm, ...) and wait for it")
    p.add_argument("--site-name")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="write the result JSON here (default stdout)")
    p.set_defaults(func=cmd_survey)

    p = sub.add_parser("track", help="K phones walk and are tracked by the server")
    _server_args(p, admin=False, device=True)
    p.add_argument("--scenario", default="open_room")
    p.add_argument("--site-id", required=True)
    p.add_argument("--phones", type=int, default=4)
    p.add_argument("--filters", default="skpf", help="comma list, assigned to phones round-robin")
    p.add_argument("--interval", type=float, default=2.0, help="seconds of phone time per batch")
    p.add_argument("--speed", type=float, default=0.0, help="1 = real time, 10 = 10x, 0 = as fast as possible")
    p.add_argument("--wifi-hz", type=float, default=1.0)
    p.add_argument("--ble-hz", type=float, default=2.0)
    p.add_argument("--no-initial", action="store_true", help="open sessions without the true start")
    p.add_argument("--retries", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="track_results.json")
    p.set_defaults(func=cmd_track)

    p = sub.add_parser("crowd", help="unsurveyed phones walk; the server's crowdsourcing builds the map")
    _server_args(p, admin=True, device=True)
    p.add_argument("--scenario", default="corridor_loop")
    p.add_argument("--site-id", help="use this site instead of creating one")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--phones", type=int, default=10)
    p.add_argument("--filter", default="skpf")
    p.add_argument("--train", default="knn", help="algorithm trained after each round ('' = none)")
    p.add_argument("--probes", type=int, default=20, help="locate probes per round")
    p.add_argument("--interval", type=float, default=2.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="crowd_results.json")
    p.set_defaults(func=cmd_crowd)

    p = sub.add_parser("demo", help="start a server on SQLite, survey a demo site, track simulated phones")
    p.add_argument("--phones", type=int, default=12)
    p.add_argument("--port", type=int, help="default: a free port")
    p.add_argument("--database-url", help="default: the server's own (SQLite file in the working directory)")
    p.add_argument("--out", default="reports/demo")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--once", action="store_true", help="stop the server after the demo instead of serving on")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("msft", help="real-data evaluation on the Microsoft site-1 F1 walks (map + replay)")
    p.add_argument("data_dir", help="msft_site1_f1 directory (or its path_data_files)")
    p.add_argument("--map-walks", help="comma list of indices or file names (default: every walk not tested)")
    p.add_argument("--test-walks", help="comma list of indices or file names (default: every --every-th from 1)")
    p.add_argument("--every", type=int, default=4, help="default split: walks 1, 1+N, 1+2N... are test walks")
    p.add_argument("--folds", type=int, help="K-fold: walk i is a test walk in fold i %% K (all walks tested; "
                                             "overrides --map-walks/--test-walks)")
    p.add_argument("--filters", default="skpf,ekf,ukf,kf,pf,fkf")
    p.add_argument("--algorithm", default="knn")
    p.add_argument("--params", help="model params as JSON, e.g. '{\"k\": 7}'")
    p.add_argument("--kinds", default="wifi", help="wifi, ble or wifi,ble")
    p.add_argument("--calibration", choices=("site", "first-segment", "none"), default="site",
                   help="PDR heading offset and Weinberg k: from the map walks (site), from each test walk's "
                        "first >=10 m of waypoints (first-segment, that window is not scored), or none")
    p.add_argument("--max-age", type=float, default=3.0, help="drop WiFi entries last seen longer ago (s)")
    p.add_argument("--interval", type=float, default=2.0, help="seconds of phone time per batch")
    p.add_argument("--initial", choices=("yes", "no", "both"), default="yes",
                   help="open sessions at the first waypoint, without it, or both")
    p.add_argument("--fix-noise", default="auto",
                   help="auto: cov_floor_m from a walk-wise cross-validation on the map walks; "
                        "model: the model's own covariances; a number: that cov_floor_m (m)")
    p.add_argument("--concurrency", type=int, default=4, help="test walks replayed at once")
    p.add_argument("--url", help="use this server instead of starting one (then give the keys)")
    p.add_argument("--admin-key", default=_env("LOCALIZER_ADMIN_KEY", "LOCALIZER_API_KEY"))
    p.add_argument("--device-key", default=_env("LOCALIZER_DEVICE_KEY", "LOCALIZER_API_KEY"))
    p.add_argument("--out", help="results JSON (a .md table is written beside it)")
    p.set_defaults(func=cmd_msft)

    p = sub.add_parser("report", help="error table, CDF and trajectory plots from track results")
    p.add_argument("results", nargs="+")
    p.add_argument("--out", default="reports/client_sim")
    p.set_defaults(func=cmd_report)
    return ap


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
