"""The demo: a real server process on SQLite, a surveyed demo site and simulated phones.

    python -m client_sim demo [--phones 8] [--once]

Starts ``python -m server serve`` on ``127.0.0.1:8000`` with the fixed development keys
``dev-admin-key`` / ``dev-device-key`` (``--port``, ``--admin-key``, ``--device-key`` to
change them) on the server's default embedded SQLite unless ``--database-url``. The demo
site (named :data:`SITE_NAME`) is surveyed and a KNN model trained on the first run only;
later runs reuse it. Then phones walk through tracking sessions with every filter, and
the report (error table, CDF and trajectory plots) goes to ``reports/demo``. The server
then keeps serving until Ctrl-C (``--once`` stops it), and the demo prints commands that
work against it as written.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shlex
import signal
import sys
import time
from pathlib import Path

from .errors import CliError
from .http_client import ApiError, LocalizerClient
from .report import markdown_table, write_report
from .runs import run_survey, run_track, survey_fingerprints
from .server_process import port_free, start_server, stop_server
from .world import get_world

FILTERS = ("skpf", "ekf", "ukf", "kf", "pf", "fkf")
SCENARIO = "open_room"
SITE_NAME = "client_sim demo: open room"
SCANS_PER_HEADING = 3


async def _model_loads(api: LocalizerClient, site_id: int) -> bool:
    """Whether the site's active model still loads: one stored by an older version of the
    service is refused (409 "train a new model"), and the demo then trains a new one."""
    transmitters = await api.request("GET", f"/api/v1/sites/{site_id}/transmitters")
    try:
        await api.locate(site_id, {t["id"]: -60.0 for t in transmitters[:3]})
    except ApiError as exc:
        return not (exc.status == 409 and "train a new model" in str(exc))
    return True


async def demo_site(url: str, admin_key: str, seed: int) -> dict:
    """The site named :data:`SITE_NAME` with its active model, surveyed and trained only if need be."""
    async with LocalizerClient(url, admin_key, key_name="admin key") as api:
        site = next((s for s in await api.list_sites() if s["name"] == SITE_NAME), None)
        if site is not None and site["fingerprints"]["survey"]:
            model = next((m for m in await api.list_models(site["id"]) if m.get("active")), None)
            if model is None or not await _model_loads(api, site["id"]):
                model = await api.wait_model(site["id"], (await api.train_model(site["id"], "wknn"))["id"])
                if model.get("status") == "ready" and not model.get("active"):
                    model = await api.activate_model(site["id"], model["id"])
            return {"site_id": site["id"], "reused": True, "accepted": site["fingerprints"]["survey"],
                    "reference_points": site["reference_points"], "model": model}
    survey = await run_survey(url, admin_key, SCENARIO, scans_per_heading=SCANS_PER_HEADING, seed=seed, train="wknn",
                              site_name=SITE_NAME, site_id=site["id"] if site else None, progress=True)
    return survey | {"reused": False}


async def run_demo(url: str, admin_key: str, device_key: str, phones: int, out_dir: Path, seed: int) -> dict:
    """Survey (or reuse) the demo site, track ``phones`` phones, write the report; returns the track result."""
    site = await demo_site(url, admin_key, seed)
    model = site.get("model") or {}
    print(f"site {site['site_id']} ({'reused' if site['reused'] else 'new'}, \"{SITE_NAME}\"): {site['accepted']} "
          f"fingerprints at {site['reference_points']} reference points; model {model.get('id')} "
          f"({model.get('algorithm')}) is {model.get('status')}")
    if model.get("status") != "ready":
        raise CliError(f"model training did not succeed: {model.get('error')}")
    out_dir.mkdir(parents=True, exist_ok=True)
    fingerprints = survey_fingerprints(get_world(SCENARIO), SCANS_PER_HEADING, seed)
    (out_dir / "survey.json").write_text(json.dumps({"fingerprints": fingerprints}))  # for the upload example
    track = await run_track(url, device_key, SCENARIO, site["site_id"], phones=phones, filters=FILTERS,
                            seed=seed, progress=True)
    (out_dir / "track.json").write_text(json.dumps(track))
    print(markdown_table(write_report([out_dir / "track.json"], out_dir)), end="")
    print(f"report written to {out_dir}/ (errors.md, cdf.png, trajectory.png; track.json, survey.json)")
    return track


def _python() -> str:
    """This interpreter, relative to the working directory when it lies below it."""
    exe = Path(sys.executable)
    try:
        return str(exe.relative_to(Path.cwd()))
    except ValueError:
        return str(exe)


def next_commands(url: str, admin_key: str, device_key: str, site_id: int, out_dir: Path) -> list[str]:
    """Shell lines that work as written against the demo's server, from the working directory."""
    py, q = shlex.quote(_python()), shlex.quote
    reports = out_dir.parent
    return [
        f"export LOCALIZER_URL={q(url)} LOCALIZER_ADMIN_KEY={q(admin_key)} LOCALIZER_DEVICE_KEY={q(device_key)}",
        f"{py} -m client_sim track --site-id {site_id} --phones 4 --filters ekf,pf "
        f"--out {q(str(reports / 'track_results.json'))}",
        f"{py} -m client_sim report {q(str(reports / 'track_results.json'))} --out {q(str(reports / 'client_sim'))}",
        f"{py} -m client_sim crowd --scenario {SCENARIO} --rounds 1 --phones 4 --probes 10 "
        f"--out {q(str(reports / 'crowd_results.json'))}",
        f"{py} -m localizer_tools.upload {q(str(out_dir / 'survey.json'))} --site {site_id} --dry-run",
        f"curl -s -H {q('Authorization: Bearer ' + admin_key)} {url}/api/v1/sites/{site_id}",
    ]


def _interrupt(*_) -> None:
    raise KeyboardInterrupt


def main(args: argparse.Namespace) -> int:
    if not port_free(args.port):
        raise CliError(f"port {args.port} is in use (a server or demo still running?): stop it or pass --port")
    env = {"LOCALIZER_ADMIN_KEYS": args.admin_key, "LOCALIZER_DEVICE_KEYS": args.device_key}
    if args.database_url:
        env["LOCALIZER_DATABASE_URL"] = args.database_url
    server = start_server(args.port, env)
    url = f"http://127.0.0.1:{args.port}"
    print(f"server up at {url} (admin key {args.admin_key}, device key {args.device_key})", flush=True)
    try:
        signal.signal(signal.SIGTERM, _interrupt)
        out_dir = Path(args.out)
        track = asyncio.run(run_demo(url, args.admin_key, args.device_key, args.phones, out_dir, args.seed))
        failed = [p for p in track["phones"] if p.get("error") or p.get("failed_posts")]
        if failed:
            raise CliError(f"{len(failed)} of {len(track['phones'])} phones failed; see {out_dir}/track.json")
        if not args.once:
            print(f"\nThe server keeps serving at {url} (API docs: {url}/docs) until Ctrl-C. "
                  "Try, in another shell in this directory:")
            for line in next_commands(url, args.admin_key, args.device_key, track["site_id"], out_dir):
                print("  " + line)
            sys.stdout.flush()
            while True:
                time.sleep(1e6)
    except KeyboardInterrupt:
        pass
    finally:
        stop_server(server)
    return 0
