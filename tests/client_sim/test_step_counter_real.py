"""The step counter on a cut of a real Oxford trace (tests/fixtures, truth from its foot sensors)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from client_sim.oxford import count_steps, evaluate, summarise

FIXTURE = Path(__file__).parents[1] / "fixtures" / "oxford_samsung_jamie_inhand_1_first24s.csv"


def test_counts_a_real_hand_held_trace():
    truth = json.loads(FIXTURE.with_suffix(".json").read_text())["true_steps"]
    assert truth == 41
    # the one step allowed is the first one from standing, which is weak on this trace
    assert abs(count_steps(FIXTURE) - truth) <= 1


def test_steps_cli_prints_the_count():
    out = subprocess.run([sys.executable, "-m", "client_sim", "steps", str(FIXTURE)], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).parents[2])
    assert out.stdout.strip() == str(count_steps(FIXTURE))


@pytest.mark.slow
def test_oxford_hand_held_error_at_most_3_percent():
    root = Path(os.environ.get("OXFORD_STEPS_DIR",
                               Path(__file__).resolve().parents[3] / "shared/data/oxford_step_counter/optimisation"))
    if not (root / "stats.csv").exists():
        pytest.skip("Oxford step counter data not available")
    table = summarise(evaluate(root))
    assert table["inhand"]["mean_error_pct"] <= 3.0
