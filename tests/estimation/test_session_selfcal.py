"""A whole simulated walk through ``SessionEstimator.apply_batch`` with a self-calibrating
filter: the PDR's heading bias is learned from the fingerprint fixes, survives the JSON the
server stores between batches, and the track beats the seed form's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from server.estimation.session import SessionEstimator
from server.estimation.types import SiteMap
from tests.estimation.test_session_walk import ModelFixes, corridor_walk


def _run(name: str, fixes: ModelFixes, seed: int = 2):
    truth, steps, scans = corridor_walk(seed=seed, laps=3)  # PDR heading +4°, steps 5 % long
    est = SessionEstimator(name, seed=1)
    est.start([0.0, 0.0], None, 0, [], None, "init")
    track, biases, t_end = [], [], 2.0
    while steps or scans:
        bs = [s for s in steps if s.t < t_end]
        bc = [s for s in scans if s.t < t_end]
        steps, scans = steps[len(bs):], scans[len(bc):]
        est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        out = est.apply_batch(bs, bc, fixes, SiteMap())
        track += [e for e in out.estimates if e.source == "step"]
        if hasattr(est.tracker, "heading_bias_deg"):
            biases += [est.tracker.heading_bias_deg] * len(bs)
        t_end += 2.0
    err = np.hypot(*(np.array([[e.x, e.y] for e in track]) - truth).T)
    return err, np.array(biases)


@pytest.fixture(scope="module")
def fixes() -> ModelFixes:
    return ModelFixes()


@pytest.mark.parametrize("name", ["ekf", "skpf"])
def test_the_heading_bias_is_learned_through_the_session(name, fixes):
    """The bias is learned on each walk, and over three walks the second halves are better
    than the seed form's (on one walk of fix-dominated tracking the two can tie)."""
    ours, seeds = [], []
    for seed in (2, 3, 4):
        err, biases = _run(name, fixes, seed)
        half = len(biases) // 2
        assert np.mean(biases[half:]) == pytest.approx(-4.0, abs=2.0), (name, seed)
        seed_err, _ = _run(f"{name}-xy", fixes, seed)
        ours.append(err[half:].mean())
        seeds.append(seed_err[half:].mean())
    assert np.mean(ours) < np.mean(seeds), (name, ours, seeds)
