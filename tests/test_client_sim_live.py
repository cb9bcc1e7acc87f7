"""client_sim against a live server over real HTTP."""

from __future__ import annotations

import asyncio
import json
import math
import re

import pytest

from client_sim.runs import run_survey
from client_sim.world import get_world
from tests.conftest import ADMIN_KEY, DEVICE_KEY


def test_survey_creates_the_scenario_site_and_stores_every_scan(admin, live_server):
    world = get_world("open_room")
    result = asyncio.run(run_survey(live_server.url, ADMIN_KEY, world, scans_per_heading=1, seed=3))
    site = admin.get(f"/api/v1/sites/{result['site_id']}").json()
    assert result["accepted"] == result["fingerprints"] == site["fingerprints"]["survey"] > 0
    assert site["reference_points"] == len(world.reference_points)
    assert site["transmitters"] == len(world.transmitters)
    assert [f["level"] for f in site["floors"]] == sorted({f.level for f in world.floors})
    points = admin.get(f"/api/v1/sites/{result['site_id']}/reference-points").json()
    assert {(p["x"], p["y"]) for p in points} == {(x, y) for x, y, _ in world.reference_points}


def test_survey_then_track_phones_through_sessions(admin, live_server):
    from client_sim.runs import run_track

    survey = asyncio.run(run_survey(live_server.url, ADMIN_KEY, "open_room", scans_per_heading=2, seed=1, train="knn"))
    assert survey["model"]["status"] == "ready"
    result = asyncio.run(run_track(live_server.url, DEVICE_KEY, "open_room", survey["site_id"], phones=2,
                                   filters=("skpf", "ekf"), seed=4))
    for phone in result["phones"]:
        assert "error" not in phone and phone["failed_posts"] == 0
        batches = phone["batch_estimates"]
        assert [b["t"] for b in batches] == sorted(b["t"] for b in batches)
        track = phone["track"]
        assert track[0]["source"] == "init" and {r["source"] for r in track[1:]} <= {"step", "scan"}
        assert len(track) > len(batches)
        mean = sum(r["error_m"] for r in track) / len(track)
        pdr = sum(r["error_m"] for r in phone["pdr_only"]) / len(phone["pdr_only"])
        assert mean < 3.0 and mean < pdr + 1.0, (phone["filter"], mean, pdr)


def test_a_tracking_run_repeats_to_the_digit_particle_filter_included(admin, live_server):
    """Sessions are seeded from the run's seed and the phone, so a PF's draws repeat too."""
    from client_sim.runs import run_track

    survey = asyncio.run(run_survey(live_server.url, ADMIN_KEY, "open_room", scans_per_heading=1, seed=2, train="knn"))

    def tracks(seed: int) -> list[list[tuple[float, float]]]:
        result = asyncio.run(run_track(live_server.url, DEVICE_KEY, "open_room", survey["site_id"], phones=1,
                                       filters=("pf",), seed=seed))
        assert all("error" not in p and p["failed_posts"] == 0 for p in result["phones"])
        return [[(r["x"], r["y"]) for r in p["track"]] for p in result["phones"]]

    first = tracks(7)
    assert tracks(7) == first
    assert tracks(8) != first


def test_crowd_rounds_grow_the_map_from_a_site_without_survey(admin, live_server):
    from client_sim.runs import run_crowd

    result = asyncio.run(run_crowd(live_server.url, ADMIN_KEY, DEVICE_KEY, "open_room", rounds=2, phones=3,
                                   probes=8, filter="ekf", train="knn", seed=2))
    bootstrap, *rounds = result["rounds"]
    assert bootstrap["model"]["algorithm"] == "propagation" and bootstrap["model"]["status"] == "ready"
    assert bootstrap["site"]["fingerprints"] == {"survey": 0, "crowd": 0}
    assert bootstrap["site"]["settings"]["crowdsourcing"] is True
    crowd = [r["site"]["fingerprints"]["crowd"] for r in rounds]
    assert 0 < crowd[0] <= crowd[1]
    assert all(r["sessions_ok"] == 3 for r in rounds)
    assert rounds[-1]["model"]["status"] == "ready" and rounds[-1]["model"]["active"] is True
    assert rounds[-1]["locate"]["answered"] == 8
    nis_mean, nis_p50 = rounds[-1]["locate"]["nis_mean"], rounds[-1]["locate"]["nis_p50"]
    assert math.isfinite(nis_mean) and nis_mean > 0 and math.isfinite(nis_p50) and nis_p50 > 0
    assert all(math.isfinite(r["tracking_nees_mean"]) and r["tracking_nees_mean"] > 0 for r in rounds)
    assert all(0.0 <= r["tracking_floor_hit_rate"] <= 1.0 for r in rounds)  # (one floor: every estimate on it)
    assert rounds[-1]["tracking_floor_hit_rate"] == 1.0


# ------------------------------------------------------------------ the CLI against a live server

def cli(capsys, *argv: str) -> tuple[int, str, list[str]]:
    """Run ``python -m client_sim`` in-process: exit code, stdout, stderr lines without progress bars."""
    from client_sim.__main__ import main

    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, [line for line in out.err.splitlines() if line.strip() and "it/s]" not in line]


@pytest.fixture
def open_room_site(admin) -> int:
    return admin.post("/api/v1/sites", json=get_world("open_room").site_payload("cli")).json()["id"]


REFUSED = "(401: unknown or revoked API key)"


@pytest.mark.parametrize("argv, message", [
    (["survey", "--admin-key", "wrong"], "{url} refused the admin key " + REFUSED),
    (["survey", "--admin-key", DEVICE_KEY],
     "{url}: the admin key may not do this (403: this endpoint needs an admin key)"),
    (["survey", "--admin-key", ADMIN_KEY, "--site-id", "987654"], "{url}: site 987654 does not exist (404)"),
    (["track", "--device-key", "wrong", "--site-id", "1"], "{url} refused the device key " + REFUSED),
    (["track", "--device-key", DEVICE_KEY, "--site-id", "987654"], "{url}: site 987654 does not exist (404)"),
    (["crowd", "--admin-key", "wrong", "--device-key", DEVICE_KEY], "{url} refused the admin key " + REFUSED),
    (["crowd", "--admin-key", ADMIN_KEY, "--device-key", "wrong"], "{url} refused the device key " + REFUSED),
    (["crowd", "--admin-key", ADMIN_KEY, "--device-key", DEVICE_KEY, "--site-id", "987654"],
     "{url}: site 987654 does not exist (404)"),
])
def test_cli_refused_key_or_unknown_site_is_one_line_and_exit_1(admin, live_server, capsys, argv, message):
    code, out, err = cli(capsys, *argv, "--url", live_server.url, "--out", "/dev/null")
    assert (code, out, err) == (1, "", ["error: " + message.format(url=live_server.url)])


def test_cli_track_prints_its_table_and_fails_when_a_phone_failed(live_server, open_room_site, capsys, tmp_path):
    out_file = tmp_path / "track.json"
    code, out, err = cli(capsys, "track", "--url", live_server.url, "--device-key", DEVICE_KEY, "--site-id",
                         str(open_room_site), "--phones", "2", "--filters", "ekf,nosuchfilter", "--out", str(out_file))
    assert code == 1
    assert "| open_room | ekf |" in out and "| open_room | pdr-only |" in out and "nosuchfilter" not in out
    assert err[0] == f"wrote {out_file}"
    assert err[1].startswith("error: 1 of 2 phones failed (phone 1: POST /api/v1/sessions -> 422")
    assert err[1].endswith(f"details in {out_file}") and len(err) == 2
    assert json.loads(out_file.read_text())["phones"][1]["error"]

    code, out, err = cli(capsys, "track", "--url", live_server.url, "--device-key", DEVICE_KEY, "--site-id",
                         str(open_room_site), "--phones", "1", "--filters", "ekf", "--out", str(out_file))
    assert code == 0 and "| open_room | ekf |" in out and err == [f"wrote {out_file}"]


def test_cli_survey_prints_the_site_and_model_and_crowd_its_rounds(admin, live_server, capsys, tmp_path):
    code, out, _ = cli(capsys, "survey", "--url", live_server.url, "--admin-key", ADMIN_KEY, "--scans", "1",
                       "--train", "knn", "--out", str(tmp_path / "survey.json"))
    site_id = json.loads((tmp_path / "survey.json").read_text())["site_id"]
    assert code == 0
    lines = out.splitlines()
    assert lines[0].startswith(f"site {site_id} (open_room): ") and "reference points" in lines[0]
    assert re.fullmatch(r"model \d+ \(knn\): ready, validation mean error [\d.]+ m, active", lines[1]), lines[1]

    code, out, _ = cli(capsys, "crowd", "--url", live_server.url, "--admin-key", ADMIN_KEY, "--device-key", DEVICE_KEY,
                       "--scenario", "open_room", "--rounds", "1", "--phones", "2", "--probes", "3", "--train", "",
                       "--out", str(tmp_path / "crowd.json"))
    assert code == 0
    lines = out.splitlines()
    assert lines[1].startswith("| round | model | crowd fingerprints |")
    assert lines[3].startswith("| bootstrap | ") and "propagation ready" in lines[3]
    assert lines[4].startswith("| 0 | ") and "| 2/2 |" in lines[4] and len(lines) == 5


def test_demo_reuses_its_site_and_prints_commands_that_work_as_written(tmp_path):
    """Two demo runs on one database: the second reuses the site; its printed commands run as they are."""
    import os
    import queue
    import subprocess
    import sys
    import threading
    from pathlib import Path

    from client_sim.server_process import free_port

    root = Path(__file__).resolve().parent.parent
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOCALIZER_")} | {"PYTHONUNBUFFERED": "1"}
    demo = [sys.executable, "-m", "client_sim", "demo", "--phones", "2", "--database-url",
            f"sqlite:///{tmp_path / 'demo.db'}", "--out", str(tmp_path / "reports" / "demo")]
    first = subprocess.run([*demo, "--once", "--port", str(free_port())], cwd=root, env=env, capture_output=True,
                           text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    assert '(new, "client_sim demo: open room")' in first.stdout and "| open_room | ekf |" in first.stdout
    assert {p.name for p in (tmp_path / "reports" / "demo").iterdir()} >= {"errors.md", "cdf.png", "trajectory.png"}

    serving = subprocess.Popen([*demo, "--port", str(free_port())], cwd=root, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True)
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in serving.stdout or ()], daemon=True).start()
    try:
        out = []
        while not out or not out[-1].startswith("  curl"):
            out.append(lines.get(timeout=300))
        text = "".join(out)
        assert '(reused, "client_sim demo: open room")' in text
        commands = [line.strip() for line in out if line.startswith("  ")]
        assert commands[0].startswith("export LOCALIZER_URL=")
        run = subprocess.run(["bash", "-ec", "\n".join(commands)], cwd=root, env=env, capture_output=True, text=True,
                             timeout=600)
        assert run.returncode == 0, run.stderr[-2000:]
        assert "| open_room | ekf |" in run.stdout and "| bootstrap |" in run.stdout  # track, report, crowd
        assert "survey.json: valid, nothing stored" in run.stdout  # upload --dry-run
        assert '"name":"client_sim demo: open room"' in run.stdout  # curl
        assert (tmp_path / "reports" / "client_sim" / "trajectory.png").exists()
    finally:
        serving.terminate()
        assert serving.wait(timeout=60) == 0


def test_the_demo_trains_a_new_model_when_its_sites_model_no_longer_loads(admin, live_server, clean_db):
    """A localizer.db from an older version keeps a model artifact the service now refuses:
    the demo then trains (and activates) a new model instead of tracking without fixes."""
    import hashlib

    from sqlalchemy import create_engine, update

    from client_sim.demo import demo_site
    from server.tables import ModelArtifact

    first = asyncio.run(demo_site(live_server.url, ADMIN_KEY, seed=1))
    assert not first["reused"] and first["model"]["status"] == "ready"
    blob = b"\x80\x04\x95an old pickle"
    engine = create_engine(clean_db)
    with engine.begin() as conn:
        conn.execute(update(ModelArtifact).values(blob=blob, sha256=hashlib.sha256(blob).hexdigest()))
    engine.dispose()
    again = asyncio.run(demo_site(live_server.url, ADMIN_KEY, seed=1))
    assert again["reused"] and again["model"]["id"] != first["model"]["id"]
    assert again["model"]["status"] == "ready" and again["model"]["active"]
    unchanged = asyncio.run(demo_site(live_server.url, ADMIN_KEY, seed=1))
    assert unchanged["model"]["id"] == again["model"]["id"]
