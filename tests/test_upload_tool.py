"""The survey upload tool against a live server: chunks, validation first, idempotent re-runs."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from localizer_tools.upload import chunks_of, guess_format, main, upload
from tests.conftest import ADMIN_KEY, DEVICE_KEY, free_port

FIXTURES = Path(__file__).parent / "fixtures"


@pytest.fixture
def site_id(admin) -> int:
    """Floors 0 and 1 of buildings 0 (the CSV and JSON surveys) and 1 (uji_tiny.csv's BUILDINGID)."""
    floors = [{"level": level, "building": b} for b in (0, 1) for level in (0, 1)]
    return admin.post("/api/v1/sites", json={"name": "Upload", "floors": floors}).json()["id"]


def run(path: Path, live_server, site_id: int, fmt: str, **options) -> tuple[int, str]:
    out = io.StringIO()
    code = upload(path, live_server.url, ADMIN_KEY, site_id, fmt, progress=False, out=out, **options)
    return code, out.getvalue()


def survey_count(admin, site_id: int) -> int:
    return admin.get(f"/api/v1/sites/{site_id}").json()["fingerprints"]["survey"]


def test_chunks_keep_the_header_and_every_row():
    chunks = list(chunks_of(FIXTURES / "uji_tiny.csv", "ujiindoorloc", 5))
    assert [c.rows for c in chunks] == [5, 5, 2]
    assert all(c.body.startswith(b"WAP001,") for c in chunks)
    assert chunks[1].first_row == 5 and chunks[1].lines == [7, 8, 9, 10, 11]
    assert guess_format(FIXTURES / "uji_tiny.csv") == "ujiindoorloc"


def test_uploads_in_chunks_and_a_rerun_stores_nothing_twice(admin, live_server, site_id):
    code, out = run(FIXTURES / "uji_tiny.csv", live_server, site_id, "ujiindoorloc", chunk_size=4)
    assert code == 0 and "11 fingerprints stored, 1 skipped" in out
    code, out = run(FIXTURES / "uji_tiny.csv", live_server, site_id, "ujiindoorloc", chunk_size=4)
    assert code == 0 and "3 chunk(s) had been stored before" in out
    assert survey_count(admin, site_id) == 11


def test_a_bad_row_in_a_late_chunk_is_reported_by_line_and_nothing_is_stored(admin, live_server, site_id, tmp_path):
    rows = ["x,y,floor,label,wifi:ap1,wifi:ap2"] + [f"{i},0,0,P{i},-50,-60" for i in range(10)]
    rows[9] = "8,0,0,P8,-50,12"  # data row 8, file line 10: RSS above 0 dBm
    rows[10] = "9,0,3,P9,-50,-60"  # data row 9, line 11: floor 3 is not a floor of the site
    path = tmp_path / "survey.csv"
    path.write_text("\n".join(rows) + "\n")
    code, out = run(path, live_server, site_id, "csv", chunk_size=3)
    assert code == 1
    assert "row 8 (line 10): rss.wifi:ap2:" in out and "row 9 (line 11): floor:" in out
    assert survey_count(admin, site_id) == 0


def test_dry_run_stores_nothing(admin, live_server, site_id, tmp_path):
    path = tmp_path / "survey.json"
    path.write_text(json.dumps({"fingerprints": [{"x": 1, "y": 2, "floor": 0, "rss": {"ble:b1": -70}}] * 5}))
    code, out = run(path, live_server, site_id, "json", chunk_size=2, dry_run=True)
    assert code == 0 and "valid, nothing stored" in out
    assert survey_count(admin, site_id) == 0
    code, _ = run(path, live_server, site_id, "json", chunk_size=2)
    assert code == 0 and survey_count(admin, site_id) == 5


# ------------------------------------------------------------------ the command line: one error line, non-zero exit

def cli(capsys, *argv: str) -> tuple[int, list[str]]:
    code = main(list(argv))
    return code, capsys.readouterr().err.strip().splitlines()


def test_cli_missing_file_or_key(capsys, monkeypatch):
    for name in ("LOCALIZER_ADMIN_KEY", "LOCALIZER_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    assert cli(capsys, "nope.csv", "--site", "1", "--key", "k") == (2, ["error: nope.csv: no such file"])
    assert cli(capsys, str(FIXTURES / "uji_tiny.csv"), "--site", "1") == (
        2, ["error: an admin key is needed: pass --key or set LOCALIZER_ADMIN_KEY (or LOCALIZER_API_KEY)"])


def test_cli_chunk_size_below_one_row(capsys):
    for size in ("0", "-5"):
        assert cli(capsys, str(FIXTURES / "uji_tiny.csv"), "--site", "1", "--key", "k", "--chunk-size", size) == (
            2, [f"error: --chunk-size must be at least 1 row, not {size}"])


def test_cli_dead_server(capsys):
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    code, err = cli(capsys, str(FIXTURES / "uji_tiny.csv"), "--site", "1", "--key", "k", "--url", url)
    assert code == 1 and len(err) == 1 and err[0].startswith(f"error: cannot connect to {url}: is the server running?")


@pytest.mark.parametrize("key, site, message", [
    ("wrong", None, "{url} refused the key (401: unknown or revoked API key)"),
    (DEVICE_KEY, None, "{url}: the key may not upload surveys, an admin key is needed (403: this endpoint needs an admin key)"),
    (ADMIN_KEY, 987654, "{url}: site 987654 does not exist (404)"),
])
def test_cli_refused_key_or_unknown_site(admin, live_server, site_id, capsys, key, site, message):
    argv = [str(FIXTURES / "uji_tiny.csv"), "--site", str(site or site_id), "--key", key, "--url", live_server.url]
    assert cli(capsys, *argv) == (1, ["error: " + message.format(url=live_server.url)])
    assert survey_count(admin, site_id) == 0


def test_cli_version_and_defaults_in_help(capsys):
    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.startswith("python -m localizer_tools.upload ")
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 2000)" in text and "(default: http" in text and "default: from the file" in text


def test_a_killed_upload_rerun_with_other_chunk_sizes_stores_every_row_exactly_once(admin, live_server, site_id, tmp_path):
    """The tool as a real process, killed (SIGKILL) part-way through storing, then run again with
    other chunk sizes: every row of the file is stored once, none lost, none doubled."""
    import os
    import signal
    import subprocess
    import sys
    import time

    total = 1200
    path = tmp_path / "big.csv"
    path.write_text("x,y,floor,label,wifi:ap1,wifi:ap2\n" + "".join(f"{i % 40},{i // 40},0,P{i},-50,-{40 + i % 50}\n"
                                                                    for i in range(total)))
    env = {**os.environ, "LOCALIZER_ADMIN_KEY": ADMIN_KEY}
    command = [sys.executable, "-m", "localizer_tools.upload", str(path), "--site", str(site_id), "--url", live_server.url,
               "--quiet", "--no-validate"]
    tool = subprocess.Popen([*command, "--chunk-size", "50"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while survey_count(admin, site_id) < 150 and tool.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    tool.send_signal(signal.SIGKILL)
    tool.wait(timeout=20)
    stored_before = -1
    while stored_before != survey_count(admin, site_id):  # the chunk in flight when it died may still be stored
        stored_before = survey_count(admin, site_id)
        time.sleep(0.5)
    assert 0 < stored_before < total, "the tool was to be killed part-way"

    def each_row_once() -> None:
        points = admin.get(f"/api/v1/sites/{site_id}/reference-points").json()
        assert sorted(p["fingerprints"] for p in points) == [1] * survey_count(admin, site_id)

    each_row_once()
    for chunk_size in ("333", "7", "5000"):
        rerun = subprocess.run([*command, "--chunk-size", chunk_size], env=env, capture_output=True, text=True, timeout=120)
        assert rerun.returncode == 0, rerun.stderr
        assert survey_count(admin, site_id) == total
        each_row_once()
    assert "0 fingerprints stored" in rerun.stdout and f"{total} row(s) had been stored by an earlier run" in rerun.stdout
