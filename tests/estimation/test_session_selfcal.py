"""A whole simulated walk through ``SessionEstimator.apply_batch`` with a self-calibrating
filter: the PDR's heading bias is learned from the fingerprint fixes, survives the JSON the
server stores between batches, and the track beats the seed form's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from server.estimation.session import SessionEstimator
from server.estimation.tracking import smooth_track
from server.estimation.types import Fix, Scan, SiteMap, Step
from tests.estimation.test_session_walk import ModelFixes, corridor_walk


def _run(name: str, fixes: ModelFixes, seed: int = 2, outage: float | None = None):
    """The walk's step errors and the learned heading bias per step; ``outage``: the scans of the
    walk's last fraction ``outage`` are dropped (a stretch without fixes)."""
    truth, steps, scans = corridor_walk(seed=seed, laps=3)  # PDR heading +4°, steps 5 % long
    if outage is not None:
        t_out = steps[int(len(steps) * (1.0 - outage))].t
        scans = [s for s in scans if s.t < t_out]
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
    """The bias is learned on each walk; then, in a lap without fixes, the dead reckoning it
    corrects drifts far less than the seed form's. (Where fixes come every 1.5 s, as in the first
    two laps, the track is fix-dominated and the two forms are within 0.1 m of each other.)"""
    ours, seeds = [], []
    for seed in (2, 3, 4):
        _, biases = _run(name, fixes, seed)
        half = len(biases) // 2
        assert np.mean(biases[half:]) == pytest.approx(-4.0, abs=2.0), (name, seed)
        err, _ = _run(name, fixes, seed, outage=1 / 3)
        seed_err, _ = _run(f"{name}-xy", fixes, seed, outage=1 / 3)
        last = len(err) * 2 // 3
        ours.append(err[last:].mean())
        seeds.append(seed_err[last:].mean())
    assert np.mean(ours) < 0.6 * np.mean(seeds), (name, ours, seeds)


class OffsetFixes:
    """Fixes at the truth plus one offset (4, 0) m for the whole walk and white noise, declared
    σ² = 10 m² with their walk share 0.8 (as a map whose training measured it would)."""

    def __init__(self, truth_by_t: dict[float, np.ndarray]):
        rng = np.random.default_rng(0)
        self.by_t = {t: p + np.array([4.0, 0.0]) + np.sqrt(2.0) * rng.standard_normal(2) for t, p in truth_by_t.items()}

    def fix(self, scan: Scan, near) -> Fix:
        z = self.by_t[scan.t]
        return Fix(float(z[0]), float(z[1]), 0, np.eye(2) * 10.0, shared_share=0.8)


def test_a_session_learns_the_walks_fix_offset_and_smooths_its_track():
    """Through the session (stored and loaded between batches, the innovation gate, the fix-noise
    scale): an EKF with ``walk_offset`` fed fixes that share one offset learns it, refuses none of them once it has,
    and its stored whole states (what the smoother reads) stay [x, y, b, s]."""
    steps = [Step(0.5 * k, 0.7, 0.0, length_std_m=0.05, heading_std_deg=2.0) for k in range(1, 61)]
    truth = {s.t + 0.1: np.array([0.0, 0.7 * k]) for k, s in enumerate(steps, 1) if k % 2 == 0}
    scans = [Scan(t, {"ap": -60.0}) for t in truth]
    fixes = OffsetFixes(truth)
    est = SessionEstimator("ekf", seed=1, tracker_params={"walk_offset": 1})
    est.start([0.0, 0.0], [[0.01, 0.0], [0.0, 0.01]], 0, [], None, "init")
    refused, states, track = 0, [], []
    for t0 in np.arange(0.0, 31.0, 2.0):
        est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        out = est.apply_batch([s for s in steps if t0 <= s.t < t0 + 2], [s for s in scans if t0 <= s.t < t0 + 2],
                              fixes, SiteMap())
        refused += len(out.rejected_fixes)
        states += list(out.states)
        track += list(out.estimates)
    assert est.tracker.has_offset
    np.testing.assert_allclose(est.tracker.fix_offset, [4.0, 0.0], atol=1.5)
    assert refused == 0
    assert {len(s.mean) for s in states} == {4}
    assert abs(float(est.tracker.mean[0])) < 1.5  # on its steps, not on the offset fixes
    smoothed = smooth_track(track, states=states)
    assert len(smoothed) == len(track) and abs(smoothed[-1].x) < 1.5
