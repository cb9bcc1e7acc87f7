"""The demo: a real server process on SQLite, a surveyed demo site and simulated phones.

    python -m client_sim demo [--phones 8] [--once]

Starts ``python -m server serve`` (the server's default embedded SQLite unless
``--database-url``), surveys the open-room scenario and trains a model over HTTP,
walks phones through tracking sessions with every filter, and writes the report
(error table, CDF and trajectory plots) to ``reports/demo``. Then it keeps the server
up for you to explore (``/docs``) until Ctrl-C, or stops with ``--once``.
"""

from __future__ import annotations

import asyncio
import json
import secrets
import signal
import time
from pathlib import Path

from .report import write_report
from .runs import run_survey, run_track
from .server_process import free_port, start_server, stop_server

FILTERS = ("skpf", "ekf", "ukf", "kf", "pf", "fkf")


async def run_demo(url: str, admin_key: str, device_key: str, phones: int, out_dir: Path, seed: int) -> Path:
    survey = await run_survey(url, admin_key, "open_room", scans_per_heading=3, seed=seed, train="knn",
                              site_name=f"demo open room {seed}")
    model = survey.get("model") or {}
    print(f"site {survey['site_id']}: {survey['accepted']} fingerprints at {survey['reference_points']} "
          f"reference points; model {model.get('id')} ({model.get('algorithm')}) is {model.get('status')}")
    if model.get("status") != "ready":
        raise SystemExit(f"model training did not succeed: {model.get('error')}")
    track = await run_track(url, device_key, "open_room", survey["site_id"], phones=phones, filters=FILTERS,
                            seed=seed, progress=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    results = out_dir / "track.json"
    results.write_text(json.dumps(track))
    write_report([results], out_dir)
    return out_dir / "errors.md"


def _interrupt(*_) -> None:
    raise KeyboardInterrupt


def main(args) -> int:
    port = args.port or free_port()
    admin_key, device_key = f"demo-admin-{secrets.token_hex(4)}", f"demo-device-{secrets.token_hex(4)}"
    env = {"LOCALIZER_ADMIN_KEYS": admin_key, "LOCALIZER_DEVICE_KEYS": device_key}
    if args.database_url:
        env["LOCALIZER_DATABASE_URL"] = args.database_url
    server = start_server(port, env)
    url = f"http://127.0.0.1:{port}"
    print(f"server up at {url} (admin key {admin_key}, device key {device_key})")
    try:
        signal.signal(signal.SIGTERM, _interrupt)
        table = asyncio.run(run_demo(url, admin_key, device_key, args.phones, Path(args.out), args.seed))
        print(table.read_text())
        print(f"report written to {args.out}/ (errors.md, cdf.png, trajectory.png)")
        while not args.once:
            print(f"serving at {url}/docs — Ctrl-C to stop")
            time.sleep(1e6)
    except KeyboardInterrupt:
        pass
    finally:
        stop_server(server)
    return 0
