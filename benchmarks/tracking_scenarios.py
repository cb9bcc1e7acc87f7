"""Every tracker on the same simulated walks, through the HTTP API, against PDR alone and
fingerprinting alone — on the good-signal (open room) and poor-signal (corridor loop) scenarios.

    python benchmarks/tracking_scenarios.py [--walks 6] [--algorithm knn] [--out reports/tracking]

Starts a real server process on a fresh SQLite file, surveys each scenario with
``client_sim`` and trains a model, then walks the same phones (same seeds: same walk,
IMU, PDR steps and scans) once per filter through tracking sessions, each walk's sessions seeded
alike (``session_seed``), so a run repeats to the digit, the particle filters included. Fingerprinting
alone is ``locate`` on every scan; PDR alone is the phone's dead reckoning from the true
start. Errors are against the simulator's ground truth at each estimate's time, and so is each
estimate's NEES (its error under its own covariance: 2 on average when the covariance is honest; for
fingerprinting alone the NIS of each ``locate`` answer).
With ``--cold`` the sessions open without ``initial`` (a cold start from their first scan). The cost
column is the tracker library's µs per step + update, measured in this process.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import secrets
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from tracker_cost import Bench, measure  # noqa: E402

from client_sim.consistency import squared_mahalanobis  # noqa: E402
from client_sim.errors import number, seed_int  # noqa: E402
from client_sim.http_client import LocalizerClient  # noqa: E402
from client_sim.phone import simulate_phone  # noqa: E402
from client_sim.radio import RadioModel  # noqa: E402
from client_sim.report import stats  # noqa: E402
from client_sim.runs import run_survey, session_seed, track_phone  # noqa: E402
from client_sim.server_process import free_port, start_server, stop_server  # noqa: E402
from client_sim.world import get_world  # noqa: E402

#: the self-calibrating filters, their two-state seed forms (``-xy``) and the linear ones
FILTERS = ("skpf", "ekf", "ukf", "pf", "skpf-xy", "ekf-xy", "ukf-xy", "pf-xy", "kf", "fkf")
SCENARIOS = {"open_room": "good signal", "corridor_loop": "poor signal"}


async def fingerprint_only(api: LocalizerClient, site_id: int, trace) -> tuple[list[float], list[float]]:
    """``locate`` on every scan of the walk: (errors, NIS of each answer under its own covariance)."""
    errors, nis = [], []
    for scan in trace.scans:
        try:
            fix = await api.locate(site_id, scan["rss"], scan.get("heading_deg"))
        except Exception:  # noqa: BLE001 - a scan hearing no known transmitter has no fix
            continue
        x, y, _ = trace.truth_at(scan["t"])
        errors.append(math.hypot(fix["x"] - x, fix["y"] - y))
        nis.append(squared_mahalanobis(fix["x"] - x, fix["y"] - y, fix["covariance"]))
    return errors, nis


async def evaluate(url: str, admin: str, device: str, scenario: str, walks: int, filters, algorithm: str,
                   seed: int, initial: bool = True) -> dict:
    world = get_world(scenario)
    survey = await run_survey(url, admin, world, scans_per_heading=3, seed=seed, train=algorithm,
                              site_name=f"{scenario} {seed}")
    if survey.get("model", {}).get("status") != "ready":
        raise SystemExit(f"{scenario}: model did not train: {survey.get('model')}")
    site_id = survey["site_id"]
    radio = RadioModel(world)
    traces = [simulate_phone(world, world.routes[w % len(world.routes)], seed * 1000 + w, radio=radio)
              for w in range(walks)]
    errors: dict[str, list[float]] = {name: [] for name in ("pdr-only", "fingerprint-only", *filters)}
    nees: dict[str, list[float]] = {name: [] for name in ("fingerprint-only", *filters)}
    async with LocalizerClient(url, device) as api:
        runs = await asyncio.gather(*(track_phone(api, site_id, trace, f, initial=initial,
                                                  session_seed=session_seed(seed, w))
                                       for w, trace in enumerate(traces) for f in filters))
        for run in runs:
            if run["failed_posts"]:
                raise SystemExit(f"{scenario}/{run['filter']}: {run['failed_posts']} failed posts")
            rows = [row for row in run["track"] if row["source"] != "init"]
            errors[run["filter"]] += [row["error_m"] for row in rows]
            nees[run["filter"]] += [row["nees"] for row in rows if "nees" in row]
        for run in runs[:: len(filters)]:  # one per walk
            errors["pdr-only"] += [row["error_m"] for row in run["pdr_only"]]
        for trace in traces:
            fp_errors, fp_nis = await fingerprint_only(api, site_id, trace)
            errors["fingerprint-only"] += fp_errors
            nees["fingerprint-only"] += fp_nis
    table = {name: stats(e) for name, e in errors.items() if e}
    for name, v in nees.items():
        if v and name in table:
            table[name] |= {"nees_mean": float(np.mean(v)), "nees_p50": float(np.median(v))}
    return {"scenario": scenario, "site_id": site_id, "walks": walks, "model": survey["model"], "initial": initial,
            "table": table}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", default=",".join(SCENARIOS))
    parser.add_argument("--walks", type=number(int, 1), default=6, help="walks per scenario (each replayed once per filter)")
    parser.add_argument("--filters", default=",".join(FILTERS))
    parser.add_argument("--algorithm", default="knn")
    parser.add_argument("--seed", type=seed_int, default=0)
    parser.add_argument("--cold", action="store_true", help="sessions without `initial` (cold start)")
    parser.add_argument("--out", default="reports/tracking")
    args = parser.parse_args()
    filters = args.filters.split(",")

    admin, device = secrets.token_hex(8), secrets.token_hex(8)
    port = free_port()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        server = start_server(port, {"LOCALIZER_DATABASE_URL": f"sqlite:///{tmp}/tracking.db",
                                     "LOCALIZER_ADMIN_KEYS": admin, "LOCALIZER_DEVICE_KEYS": device})
        try:
            for scenario in args.scenarios.split(","):
                results.append(asyncio.run(evaluate(f"http://127.0.0.1:{port}", admin, device, scenario,
                                                    args.walks, filters, args.algorithm, args.seed,
                                                    initial=not args.cold)))
        finally:
            stop_server(server)
    cost = measure({name: Bench(name, 300) for name in filters})

    lines = []
    for res in results:
        lines.append(f"\n{res['scenario']} ({SCENARIOS.get(res['scenario'], '')}), {res['walks']} walks, "
                     f"model {res['model']['algorithm']}{'' if res['initial'] else ', cold start'}")
        lines.append("| method | mean m | std m | p50 m | p90 m | max m | NEES mean / p50 | estimates | µs/step+update |")
        lines.append("|---|---|---|---|---|---|---|---|---|")
        for name, s in res["table"].items():
            c = cost.get(name)
            us = f"{c['predict_us'] + c['update_us']:.0f}" if c else "—"
            nees = f"{s['nees_mean']:.1f} / {s['nees_p50']:.1f}" if "nees_mean" in s else "—"
            lines.append(f"| {name} | {s['mean']:.2f} | {s['std']:.2f} | {s['p50']:.2f} | {s['p90']:.2f} "
                         f"| {s['max']:.2f} | {nees} | {s['n']} | {us} |")
    if "pf" in cost and "skpf" in cost:
        pf, sk = cost["pf"], cost["skpf"]
        lines.append(f"\nPF-1000 / SKPF cost per step+update: "
                     f"{(pf['predict_us'] + pf['update_us']) / (sk['predict_us'] + sk['update_us']):.1f}x")
    text = "\n".join(lines)
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tracking.md").write_text(text + "\n")  # beside the JSON, under --out
    (out / "tracking.json").write_text(json.dumps({"results": results, "cost_us": cost}, indent=1))


if __name__ == "__main__":
    main()
