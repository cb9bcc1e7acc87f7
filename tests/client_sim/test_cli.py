"""``python -m client_sim`` without a server: help, --version, missing files and keys, a dead server.

Every failure a user can fix is one ``error:`` line on stderr and a non-zero exit (2: usage).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

from client_sim.__main__ import HelpFormatter, build_parser, main
from client_sim.server_process import free_port

ROOT = Path(__file__).resolve().parents[2]


def one_error(capsys: pytest.CaptureFixture[str]) -> str:
    """The single stderr line (nothing else on stderr), without its ``error: `` prefix."""
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0].removeprefix("error: ")


def parsers() -> list[argparse.ArgumentParser]:
    top = build_parser()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    return [top, *sub.choices.values()]


def test_every_option_has_help_showing_its_default():
    for parser in parsers():
        formatter = HelpFormatter(parser.prog)
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction | argparse._VersionAction | argparse._SubParsersAction):
                continue
            text = formatter._get_help_string(action)
            assert text, (parser.prog, action.dest)
            if action.option_strings and action.default not in (None, False):
                assert "default" in text, (parser.prog, action.dest, text)


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith("python -m client_sim ")


@pytest.mark.parametrize("argv, message", [
    (["steps", "nope.csv"], "nope.csv: no such file"),
    (["report", "nope.json"], "nope.json: No such file or directory"),
    (["eval-steps", "nope"], "nope: no stats.csv there"),
    (["scenario", "nope.json"], "nope.json: neither a scenario (open_room, corridor_loop, multi_floor) nor a world file"),
    (["survey", "--admin-key", "k", "--scenario", "nope.json"], "nope.json: neither a scenario"),
])
def test_a_missing_file_is_one_line_and_exit_2(capsys, argv, message):
    assert main(argv) == 2
    assert one_error(capsys).startswith(message)


def test_a_results_file_without_track_results_is_an_error(capsys, tmp_path):
    path = tmp_path / "crowd.json"
    path.write_text('{"kind": "crowd", "rounds": []}')
    assert main(["report", str(path), "--out", str(tmp_path / "rep")]) == 1
    assert one_error(capsys) == f"no track results in {path}"


@pytest.mark.parametrize("argv, message", [
    (["survey"], "an admin key is needed: pass --admin-key or set LOCALIZER_ADMIN_KEY (or LOCALIZER_API_KEY)"),
    (["track", "--site-id", "1"], "a device key is needed: pass --device-key or set LOCALIZER_DEVICE_KEY"),
    (["crowd", "--admin-key", "a"], "a device key is needed"),
])
def test_a_missing_key_is_one_line_and_exit_2(capsys, monkeypatch, argv, message):
    for name in ("LOCALIZER_ADMIN_KEY", "LOCALIZER_DEVICE_KEY", "LOCALIZER_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    assert main(argv) == 2
    assert one_error(capsys).startswith(message)


@pytest.mark.parametrize("argv", [
    ["survey", "--admin-key", "a"],
    ["track", "--device-key", "d", "--site-id", "1"],
    ["crowd", "--admin-key", "a", "--device-key", "d"],
    ["msft", "nowhere", "--admin-key", "a", "--device-key", "d"],
])
def test_a_dead_server_is_one_line_and_exit_1(capsys, argv):
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    assert main([*argv, "--url", url]) == 1
    assert one_error(capsys).startswith(f"cannot connect to {url}: is the server running?")


def test_the_module_entry_point_exits_without_a_traceback():
    url = f"http://127.0.0.1:{free_port()}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("LOCALIZER_")}
    run = subprocess.run([sys.executable, "-m", "client_sim", "track", "--site-id", "1", "--device-key", "d",
                          "--url", url], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 1
    [line] = run.stderr.splitlines()
    assert line.startswith(f"error: cannot connect to {url}: is the server running?")


def test_demo_on_a_taken_port_is_one_line_and_exit_1(capsys):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["demo", "--port", str(port), "--once"]) == 1
    assert one_error(capsys) == f"port {port} is in use (a server or demo still running?): stop it or pass --port"


@pytest.mark.parametrize("only", ["a", "0,x", "7"])
def test_msft_only_folds_that_are_not_fold_numbers_are_one_line_and_exit_2(capsys, tmp_path, only):
    (tmp_path / "walk.txt").write_text("")
    argv = ["msft", str(tmp_path), "--folds", "4", "--only-folds", only]  # refused before any server starts
    assert main(argv) == 2
    assert one_error(capsys).startswith(f"--only-folds {only!r}")


@pytest.mark.parametrize("params", ["{pf", "[1]", '{"pf": 1}'])
def test_msft_filter_params_that_are_not_an_object_of_objects_are_one_line_and_exit_2(capsys, tmp_path, params):
    (tmp_path / "walk.txt").write_text("")
    argv = ["msft", str(tmp_path), "--folds", "4", "--filter-params", params]  # refused before any server starts
    assert main(argv) == 2
    assert one_error(capsys).startswith("--filter-params")


@pytest.mark.parametrize("argv", [["demo", "--once", "--seed", "-1"], ["scenario", "open_room", "--seed", "x"],
                                  ["track", "--scenario", "open_room", "--site-id", "1", "--seed", "-3"]])
def test_a_seed_that_is_not_a_non_negative_integer_is_a_usage_error(capsys, argv):
    with pytest.raises(SystemExit) as e:  # refused by the parser, before any server or numpy generator
        main(argv)
    assert e.value.code == 2
    assert "argument --seed: must be an integer ≥ 0, not" in capsys.readouterr().err


@pytest.mark.parametrize("argv, option, message", [
    (["msft", ".", "--interval", "0"], "--interval", "must be a number > 0, not '0'"),
    (["track", "--scenario", "open_room", "--site-id", "1", "--interval", "nan"], "--interval", "must be a number > 0"),
    (["track", "--scenario", "open_room", "--site-id", "1", "--phones", "0"], "--phones", "must be an integer ≥ 1"),
    (["crowd", "--scenario", "open_room", "--probes", "-1"], "--probes", "must be an integer ≥ 0"),
    (["msft", ".", "--folds", "1"], "--folds", "must be an integer ≥ 2, not '1'"),
    (["demo", "--port", "70000"], "--port", "must be an integer ≥ 1 and ≤ 65535"),
])
def test_a_count_or_interval_out_of_range_is_a_usage_error(capsys, argv, option, message):
    """Refused by the parser, before any server starts (a zero interval divided by zero before)."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert f"argument {option}: {message}" in capsys.readouterr().err
