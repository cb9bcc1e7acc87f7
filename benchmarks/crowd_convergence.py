"""Crowdsourcing from nothing: does a site without a survey get better cold-start fixes as
crowd data grows?

    python benchmarks/crowd_convergence.py [--scenario corridor_loop] [--rounds 4] [--phones 10]

Starts a real server process (fresh SQLite), creates the scenario's site with transmitter
positions but no survey, turns crowdsourcing on and trains a path-loss (propagation)
model as the only source of fixes. Then, per round, unsurveyed phones walk in sessions
without ``initial`` (cold start from their first scan), the server stores their confident
estimates as crowd fingerprints, a KNN model is trained on the crowd data and activated,
and ``locate`` is probed with fresh scans at known spots: that error is the cold-start fix
a new phone would get, and the NIS of those answers (their error under their own covariance; 2 on
average when honest) says whether the covariance served with them can be trusted; the round's
sessions are scored the same way (tracking error, NEES, and the share of estimates on the true floor).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import secrets
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from client_sim.errors import seed_int  # noqa: E402
from client_sim.runs import run_crowd  # noqa: E402
from client_sim.server_process import free_port, start_server, stop_server  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="corridor_loop")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--phones", type=int, default=10)
    parser.add_argument("--probes", type=int, default=40)
    parser.add_argument("--filter", default="ekf")
    parser.add_argument("--seed", type=seed_int, default=0)
    parser.add_argument("--out", default="reports/crowd.json")
    args = parser.parse_args()

    admin, device = secrets.token_hex(8), secrets.token_hex(8)
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        server = start_server(port, {"LOCALIZER_DATABASE_URL": f"sqlite:///{tmp}/crowd.db",
                                     "LOCALIZER_ADMIN_KEYS": admin, "LOCALIZER_DEVICE_KEYS": device})
        try:
            result = asyncio.run(run_crowd(f"http://127.0.0.1:{port}", admin, device, args.scenario,
                                           rounds=args.rounds, phones=args.phones, filter=args.filter,
                                           train="knn", probes=args.probes, seed=args.seed, progress=True))
        finally:
            stop_server(server)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"{args.scenario}, {args.phones} phones per round ({args.filter}), {args.probes} locate probes per round")
    print("| after round | model | crowd fingerprints | cold-start fix mean m | fix NIS mean / p50 | floor hit "
          "| tracking mean m | tracking NEES mean / p50 | tracking floor hit |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in result["rounds"]:
        loc = r["locate"]
        mean = f"{loc['mean_error_m']:.2f}" if loc["mean_error_m"] is not None else "—"
        nis = f"{loc['nis_mean']:.1f} / {loc['nis_p50']:.1f}" if loc.get("nis_mean") is not None else "—"
        floor = f"{loc['floor_hit_rate']:.0%}" if loc["floor_hit_rate"] is not None else "—"
        track = r.get("tracking_mean_error_m")
        nees = (f"{r['tracking_nees_mean']:.1f} / {r['tracking_nees_p50']:.1f}" if r.get("tracking_nees_mean") is not None
                else "—")
        tfloor = f"{r['tracking_floor_hit_rate']:.0%}" if r.get("tracking_floor_hit_rate") is not None else "—"
        label = "none (bootstrap)" if r["round"] < 0 else str(r["round"] + 1)
        print(f"| {label} | {r.get('model', {}).get('algorithm', '—')} | {r['site']['fingerprints']['crowd']} "
              f"| {mean} | {nis} | {floor} | {'—' if track is None else f'{track:.2f}'} | {nees} | {tfloor} |")


if __name__ == "__main__":
    main()
