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
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from tqdm import tqdm

from .errors import EXIT_USAGE, CliError, explain, number, seed_int
from .http_client import LocalizerClient


def package_version() -> str:
    try:
        return version("localizer")
    except PackageNotFoundError:
        return "unknown"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Appends ``(default: X)`` to an option's help unless X is None/False or the help names it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default is None or action.default is False or "default" in text:
            return text
        return super()._get_help_string(action) or text


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
                       help="admin key (default: env LOCALIZER_ADMIN_KEY, else LOCALIZER_API_KEY)")
    if device:
        p.add_argument("--device-key", default=_env("LOCALIZER_DEVICE_KEY", "LOCALIZER_API_KEY"),
                       help="device key (default: env LOCALIZER_DEVICE_KEY, else LOCALIZER_API_KEY)")


def _key(a: argparse.Namespace, name: str) -> str:
    """The ``admin_key`` / ``device_key`` option, or a usage error naming where to give it."""
    key = getattr(a, name)
    if not key:
        kind = name.split("_")[0]
        article = "an" if kind == "admin" else "a"
        raise CliError(f"{article} {kind} key is needed: pass --{kind}-key or set LOCALIZER_{kind.upper()}_KEY "
                       "(or LOCALIZER_API_KEY)", EXIT_USAGE)
    return key


def _check(url: str, key: str, key_name: str, site_id: int | None = None, admin: bool = False) -> None:
    """Fail fast (before simulating anything) on a dead server, a refused key or an unknown site."""
    async def run() -> None:
        async with LocalizerClient(url, key, key_name=key_name) as api:
            await api.check(site_id, admin)

    asyncio.run(run())


def _write(path: str | None, data: dict) -> None:
    text = json.dumps(data, indent=1)
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(text)
        print(f"wrote {path}", file=sys.stderr)
    else:
        print(text)


def cmd_steps(a: argparse.Namespace) -> int:
    from .oxford import count_steps

    for f in a.files:
        if not Path(f).is_file():
            raise CliError(f"{f}: no such file", EXIT_USAGE)
    for f in a.files:
        print(count_steps(f) if len(a.files) == 1 else f"{f}\t{count_steps(f)}")
    return 0


def cmd_eval_steps(a: argparse.Namespace) -> int:
    from .oxford import evaluate, summarise

    if not (Path(a.data_dir) / "stats.csv").is_file():
        raise CliError(f"{a.data_dir}: no stats.csv there (the Oxford step-counter set's directory?)", EXIT_USAGE)
    results = evaluate(a.data_dir, progress=lambda rows: tqdm(rows, desc="traces"))
    table = summarise(results)
    print("| position | traces | mean abs count error (%) | max (%) |\n|---|---|---|---|")
    for pos, s in table.items():
        print(f"| {pos} | {s['traces']} | {s['mean_error_pct']:.2f} | {s['max_error_pct']:.2f} |")
    if a.json:
        _write(a.json, {"table": table, "traces": [r.__dict__ | {"error_pct": r.error_pct} for r in results]})
    return 0


def cmd_scenario(a: argparse.Namespace) -> int:
    from .report import plot_scenario
    from .world import get_world

    world = get_world(a.scenario)
    if a.json:
        world.to_json(a.json)
    if a.png:
        plot_scenario(world, a.png, a.seed)
    if not (a.json or a.png):
        print(json.dumps(world.site_payload(), indent=1))
    return 0


def cmd_survey(a: argparse.Namespace) -> int:
    from .runs import run_survey
    from .world import get_world

    key, world = _key(a, "admin_key"), get_world(a.scenario)
    _check(a.url, key, "admin key", a.site_id, admin=True)
    res = asyncio.run(run_survey(a.url, key, world, scans_per_heading=a.scans, seed=a.seed, train=a.train,
                                 site_name=a.site_name, site_id=a.site_id, progress=True))
    print(f"site {res['site_id']} ({res['scenario']}): {res['accepted']} of {res['fingerprints']} fingerprints stored "
          f"at {res['reference_points']} reference points")
    model = res.get("model")
    if model:
        mean = (model.get("metrics") or {}).get("mean_error_m")
        print(f"model {model['id']} ({model['algorithm']}): {model['status']}"
              + (f", validation mean error {mean:.2f} m" if mean is not None else "")
              + (", active" if model.get("active") else ""))
    _write(a.out, res)
    if model and model["status"] != "ready":
        raise CliError(f"model {model['id']} ({model['algorithm']}) is {model['status']}: "
                       f"{model.get('error') or 'not ready in time'}")
    return 0


def failed_phones(res: dict) -> str | None:
    """None when every phone of a ``track`` result went through, else what went wrong."""
    failed = [p for p in res["phones"] if p.get("error") or p.get("failed_posts")]
    if not failed:
        return None
    first = failed[0]
    why = first.get("error") or f"{first['failed_posts']} requests failed"
    return f"{len(failed)} of {len(res['phones'])} phones failed (phone {first['phone']}: {why})"


def cmd_track(a: argparse.Namespace) -> int:
    from .report import markdown_table, track_table
    from .runs import run_track
    from .world import get_world

    key, world = _key(a, "device_key"), get_world(a.scenario)
    _check(a.url, key, "device key", a.site_id)
    res = asyncio.run(run_track(a.url, key, world, a.site_id, phones=a.phones,
                                filters=a.filters.split(","), seed=a.seed, interval_s=a.interval, speed=a.speed,
                                wifi_hz=a.wifi_hz, ble_hz=a.ble_hz, initial=not a.no_initial, retries=a.retries,
                                progress=True))
    _write(a.out, res)
    print(markdown_table(track_table([res])), end="")
    failed = failed_phones(res)
    if failed:
        raise CliError(f"{failed}; details in {a.out}")
    return 0


def cmd_crowd(a: argparse.Namespace) -> int:
    from .report import crowd_table
    from .runs import run_crowd
    from .world import get_world

    admin, device, world = _key(a, "admin_key"), _key(a, "device_key"), get_world(a.scenario)
    _check(a.url, admin, "admin key", a.site_id, admin=True)
    _check(a.url, device, "device key")
    res = asyncio.run(run_crowd(a.url, admin, device, world, rounds=a.rounds, phones=a.phones,
                                filter=a.filter, seed=a.seed, train=a.train or None, probes=a.probes,
                                site_id=a.site_id, interval_s=a.interval, progress=True))
    _write(a.out, res)
    print(f"site {res['site_id']} ({res['scenario']}):")
    print(crowd_table(res), end="")
    return 0


def cmd_report(a: argparse.Namespace) -> int:
    from .report import markdown_table, write_report

    try:
        table = write_report(a.results, a.out)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    print(markdown_table(table), end="")
    print(f"wrote {a.out}/ (errors.md, errors.json, cdf.png, trajectory.png)", file=sys.stderr)
    return 0


def cmd_demo(a: argparse.Namespace) -> int:
    from .demo import main as demo

    return demo(a)


def cmd_msft(a: argparse.Namespace) -> int:
    from .msft_eval import main as msft

    if a.url:
        admin, device = _key(a, "admin_key"), _key(a, "device_key")
        _check(a.url, admin, "admin key", admin=True)
        _check(a.url, device, "device key")
    return msft(a)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m client_sim", description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, about: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=about, description=about, formatter_class=HelpFormatter)

    p = command("steps", "count steps in accelerometer CSV file(s) (time_ns, [acc,] x, y, z)")
    p.add_argument("files", nargs="+", help="accelerometer CSV file(s)")
    p.set_defaults(func=cmd_steps)

    p = command("eval-steps", "step-count error per phone position on the Oxford set")
    p.add_argument("data_dir", help="directory with stats.csv and data/<trace>/accelerometer.csv")
    p.add_argument("--json", help="also write per-trace results here")
    p.set_defaults(func=cmd_eval_steps)

    p = command("scenario", "export a scenario as JSON and/or plot its floor plan with a walk")
    p.add_argument("scenario", help="open_room | corridor_loop | multi_floor | path/to/world.json")
    p.add_argument("--json", help="write the world as JSON here")
    p.add_argument("--png", help="plot the floor plan(s) with one walk here")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the plotted walk")
    p.set_defaults(func=cmd_scenario)

    p = command("survey", "create the scenario's site and upload a survey")
    _server_args(p, admin=True, device=False)
    p.add_argument("--scenario", default="open_room", help="open_room | corridor_loop | multi_floor | world.json")
    p.add_argument("--scans", type=number(int, 1), default=5, help="scans per heading per reference point")
    p.add_argument("--train", help="request a model with this algorithm (nbc, knn, svm, ...) and wait for it")
    p.add_argument("--site-name", help="name of the new site (default: the scenario's name)")
    p.add_argument("--site-id", type=int, help="upload into this site instead of creating one")
    p.add_argument("--seed", type=seed_int, default=0, help="survey noise seed")
    p.add_argument("--out", default="reports/survey_results.json", help="result JSON")
    p.set_defaults(func=cmd_survey)

    p = command("track", "K phones walk and are tracked by the server")
    _server_args(p, admin=False, device=True)
    p.add_argument("--scenario", default="open_room", help="open_room | corridor_loop | multi_floor | world.json")
    p.add_argument("--site-id", type=int, required=True, help="the scenario's site on the server (from survey)")
    p.add_argument("--phones", type=number(int, 1), default=4, help="phones walking at once")
    p.add_argument("--filters", default="skpf", help="comma list, assigned to phones round-robin")
    p.add_argument("--interval", type=number(float, 0, above=True), default=2.0, help="seconds of phone time per batch")
    p.add_argument("--speed", type=number(float, 0), default=0.0, help="1 = real time, 10 = 10x, 0 = as fast as possible")
    p.add_argument("--wifi-hz", type=number(float, 0), default=1.0, help="WiFi scans per second")
    p.add_argument("--ble-hz", type=number(float, 0), default=2.0, help="BLE scans per second")
    p.add_argument("--no-initial", action="store_true", help="open sessions without the true start")
    p.add_argument("--retries", type=number(int, 0), default=4, help="re-sends of a failed batch (same seq)")
    p.add_argument("--seed", type=seed_int, default=0, help="walks, gaits and radio noise seed")
    p.add_argument("--out", default="reports/track_results.json", help="result JSON (input of report)")
    p.set_defaults(func=cmd_track)

    p = command("crowd", "unsurveyed phones walk; the server's crowdsourcing builds the map")
    _server_args(p, admin=True, device=True)
    p.add_argument("--scenario", default="corridor_loop", help="open_room | corridor_loop | multi_floor | world.json")
    p.add_argument("--site-id", type=int, help="use this site instead of creating one")
    p.add_argument("--rounds", type=number(int, 0), default=3, help="rounds of walks, each followed by training")
    p.add_argument("--phones", type=number(int, 1), default=10, help="phones per round")
    p.add_argument("--filter", default="skpf", help="the sessions' tracker")
    p.add_argument("--train", default="knn", help="algorithm trained after each round ('' = none)")
    p.add_argument("--probes", type=number(int, 0), default=20, help="locate probes per round")
    p.add_argument("--interval", type=number(float, 0, above=True), default=2.0, help="seconds of phone time per batch")
    p.add_argument("--seed", type=seed_int, default=0, help="walks and radio noise seed")
    p.add_argument("--out", default="reports/crowd_results.json", help="result JSON")
    p.set_defaults(func=cmd_crowd)

    p = command("demo", "start a server on SQLite, survey a demo site, track simulated phones, keep serving")
    p.add_argument("--phones", type=number(int, 1), default=12, help="phones tracked (filters round-robin)")
    p.add_argument("--port", type=number(int, 1, high=65535), default=8000, help="the server's port on 127.0.0.1")
    p.add_argument("--admin-key", default="dev-admin-key", help="the server's admin key")
    p.add_argument("--device-key", default="dev-device-key", help="the server's device key")
    p.add_argument("--database-url", help="default: the server's own (SQLite localizer.db in the repository)")
    p.add_argument("--out", default="reports/demo", help="report directory")
    p.add_argument("--seed", type=seed_int, default=0, help="survey and walks seed")
    p.add_argument("--once", action="store_true", help="stop the server after the report instead of serving on")
    p.set_defaults(func=cmd_demo)

    p = command("msft", "real-data evaluation on the Microsoft site-1 F1 walks (map + replay)")
    p.add_argument("data_dir", help="msft_site1_f1 directory (or its path_data_files)")
    p.add_argument("--map-walks", help="comma list of indices or file names (default: every walk not tested)")
    p.add_argument("--test-walks", help="comma list of indices or file names (default: every --every-th from 1)")
    p.add_argument("--every", type=number(int, 2), default=4, help="default split: walks 1, 1+N, 1+2N... are test walks")
    p.add_argument("--folds", type=number(int, 2), help="K-fold: walk i is a test walk in fold i %% K (all walks tested; "
                                             "overrides --map-walks/--test-walks)")
    p.add_argument("--filters", default="skpf,ekf,ukf,kf,pf,fkf", help="trackers replayed")
    p.add_argument("--algorithm", default="knn", help="fingerprint model")
    p.add_argument("--params", help="model params as JSON, e.g. '{\"k\": 7}'")
    p.add_argument("--kinds", default="wifi", help="wifi, ble or wifi,ble")
    p.add_argument("--calibration", choices=("site", "first-segment", "walk", "none"), default="site",
                   help="PDR heading offset and Weinberg k: from the map walks (site), from each test walk's "
                        "first >=10 m of waypoints (first-segment, that window is not scored), from the test "
                        "walk's own waypoints (walk: an oracle, a diagnostic), or none")
    p.add_argument("--heading", choices=("gyro", "kalman", "quasi-static", "qekf"), default="gyro",
                   help="the phones' PDR heading: the gyro aligned once by the compass (gyro), gyro + compass "
                        "Kalman (kalman), compass in undisturbed field only (quasi-static), gyro + gravity (qekf)")
    p.add_argument("--max-age", type=number(float, 0, above=True), default=3.0, help="drop WiFi entries last seen longer ago (s)")
    p.add_argument("--interval", type=number(float, 0, above=True), default=2.0, help="seconds of phone time per batch")
    p.add_argument("--initial", choices=("yes", "no", "both"), default="yes",
                   help="open sessions at the first waypoint, without it, or both")
    p.add_argument("--fix-noise", default="auto",
                   help="auto: cov_floor_m from a walk-wise cross-validation on the map walks; "
                        "model: the model's own covariances; a number: that cov_floor_m (m)")
    p.add_argument("--step-noise", choices=("site", "white", "none"), default="site",
                   help="the step noise the phones declare: the map walks' per-segment spread (site), its part "
                        "about each walk's median (white), or no std fields, the server's defaults (none)")
    p.add_argument("--no-session-scans", action="store_true",
                   help="sessions get the steps only, no scans (a diagnostic: the trackers without any fix)")
    p.add_argument("--concurrency", type=number(int, 1), default=4, help="test walks replayed at once")
    p.add_argument("--only-folds", help="with --folds: run only these folds (comma list, e.g. 0,1)")
    p.add_argument("--plan", default="none", help="floor plan variants, comma list of none, walls (stores and "
                                                  "outline as walls), walkable (walls + walkable area)")
    p.add_argument("--plan-margin", type=number(float, 0), default=0.0, help="grow the plan's stores by this much (m)")
    p.add_argument("--seed-salt", type=int, help="seed each session from its walk and this number (the sessions' "
                   "seed extension): two runs with the same salt use the same random draws walk by walk")
    p.add_argument("--filter-params", help="tracker parameters per filter (the sessions' filter_params extension), "
                   "JSON, e.g. '{\"pf\": {\"q\": 0.04}}': compare settings on the same walks (with --seed-salt, "
                   "the same draws)")
    p.add_argument("--smoothed", action="store_true",
                   help="also score each session's smoothed track (GET .../track?smoothed=true; "
                        "a pf session's also with smoother=particles)")
    p.add_argument("--initial-heading-std", type=number(float, 0, above=True), default=None, metavar="DEG",
                   help="open sessions with each walk's true start direction and this sigma (initial.heading_std_deg: "
                        "a phone that knows which way it starts); adds pdr-aligned, the PDR turned by the same knowledge")
    p.add_argument("--url", help="use this server instead of starting one (then give the keys)")
    p.add_argument("--admin-key", default=_env("LOCALIZER_ADMIN_KEY", "LOCALIZER_API_KEY"),
                   help="with --url (default: env LOCALIZER_ADMIN_KEY, else LOCALIZER_API_KEY)")
    p.add_argument("--device-key", default=_env("LOCALIZER_DEVICE_KEY", "LOCALIZER_API_KEY"),
                   help="with --url (default: env LOCALIZER_DEVICE_KEY, else LOCALIZER_API_KEY)")
    p.add_argument("--out", help="results JSON (a .md table is written beside it; default: print only)")
    p.set_defaults(func=cmd_msft)

    p = command("report", "error table, CDF and trajectory plots from track results")
    p.add_argument("results", nargs="+", help="track result JSON file(s)")
    p.add_argument("--out", default="reports/client_sim", help="report directory")
    p.set_defaults(func=cmd_report)
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run one command; a failure the user can fix is one ``error:`` line on stderr and a non-zero exit."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        err = explain(exc, getattr(args, "url", None))
        if err is None:
            raise
        print(f"error: {err}", file=sys.stderr)
        return err.code


if __name__ == "__main__":
    sys.exit(main())
