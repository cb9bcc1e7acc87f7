"""A whole simulated walk through ``SessionEstimator.apply_batch``: no server, no database.

A 40 × 20 m corridor loop with six WiFi APs (log-distance radio with per-scan noise), a
KNN model fitted on a survey every 2 m, and a phone whose PDR has a heading bias and a
step-length error. The walk is fed in 2 s batches; between batches the estimator goes
through JSON, as the server stores it.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from server.estimation.fingerprint import FingerprintSet, make_model
from server.estimation.session import SessionEstimator
from server.estimation.tracking import tracker_names
from server.estimation.types import Area, BatchOutcome, Fix, LateInputs, NoFix, Scan, SiteMap, Step, step_displacement

APS = {"wifi:a": (0.0, 0.0), "wifi:b": (40.0, 0.0), "wifi:c": (0.0, 20.0), "wifi:d": (40.0, 20.0),
       "wifi:e": (20.0, 10.0), "wifi:f": (20.0, -5.0)}


def rss_at(x: float, y: float, rng: np.random.Generator | None = None) -> dict[str, float]:
    noise = (lambda: 0.0) if rng is None else (lambda: float(rng.normal(0.0, 3.0)))
    return {k: -40.0 - 25.0 * math.log10(max(math.hypot(x - ax, y - ay), 1.0)) + noise() for k, (ax, ay) in APS.items()}


class ModelFixes:
    """A fitted fingerprint model as the estimator's fix source; counts the restricted queries."""

    def __init__(self):
        rows = [{"x": float(x), "y": float(y), "floor": 0, "rss": rss_at(x, y)}
                for x in range(0, 41, 2) for y in range(0, 21, 2) if x in (0, 40) or y in (0, 20)]
        self.model = make_model("knn", {}, use_heading=False, kinds=None).fit(FingerprintSet.from_rows(rows))
        self.restricted = 0

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        if not scan.rss:
            raise NoFix("the scan heard nothing")
        self.restricted += near is not None
        return self.model.locate(scan.rss, near=None if near is None else (near.x, near.y),
                                 radius_m=None if near is None else near.radius_m)


def corridor_walk(seed: int, laps: int = 2, step_m: float = 0.7):
    """True positions after each step, and the phone's steps and scans (a scan every 3 steps)."""
    rng = np.random.default_rng(seed)
    corners = [(0.0, 0.0), (40.0, 0.0), (40.0, 20.0), (0.0, 20.0)]
    pos, truth, steps, scans, t = np.array(corners[0]), [], [], [], 0.0
    for _ in range(laps):
        for k in range(4):
            a, b = np.array(corners[k]), np.array(corners[(k + 1) % 4])
            heading = math.degrees(math.atan2(b[0] - a[0], b[1] - a[1])) % 360.0
            for _ in range(int(round(np.hypot(*(b - a)) / step_m))):
                t += 0.5
                pos = pos + step_displacement(step_m, heading)
                truth.append(pos)
                steps.append(Step(t, step_m * 1.05 + rng.normal(0, 0.03), heading + 4.0 + rng.normal(0, 3.0)))
                if len(steps) % 3 == 0:
                    scans.append(Scan(t + 0.1, rss_at(*pos, rng)))
    return np.array(truth), steps, scans


def run(name: str, truth, steps, scans, fixes, initial: bool, **params) -> tuple[list, list[BatchOutcome]]:
    est = SessionEstimator(name, seed=1, tracker_params=params)
    if initial:
        est.start([0.0, 0.0], None, 0, [], None, "init")
    outcomes, t_end = [], 2.0
    while steps or scans:
        batch_steps = [s for s in steps if s.t < t_end]
        batch_scans = [s for s in scans if s.t < t_end]
        steps, scans = steps[len(batch_steps):], scans[len(batch_scans):]
        est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        outcomes.append(est.apply_batch(batch_steps, batch_scans, fixes, SiteMap()))
        t_end += 2.0
    track = [e for o in outcomes for e in o.estimates if e.source == "step"]
    return track, outcomes


@pytest.fixture(scope="module")
def fixes() -> ModelFixes:
    return ModelFixes()


@pytest.mark.parametrize("name", tracker_names())
def test_a_whole_walk_tracks_better_than_its_dead_reckoning(name, fixes):
    truth, steps, scans = corridor_walk(seed=2)
    track, outcomes = run(name, truth, steps, scans, fixes, initial=True)
    assert len(track) == len(steps)  # one estimate per step, in time order
    assert all(a.t <= b.t for a, b in zip(track, track[1:], strict=False))
    assert sum(o.applied_scans for o in outcomes) == len(scans)
    err = np.hypot(*(np.array([[e.x, e.y] for e in track]) - truth).T)
    pdr = np.cumsum([step_displacement(s.length_m, s.heading_deg) for s in steps], axis=0)
    pdr_err = np.hypot(*(pdr - truth).T)
    assert err.mean() < 0.6 * pdr_err.mean(), (name, err.mean(), pdr_err.mean())
    assert err.max() < 8.0


def test_a_tracker_that_bounds_its_search_passes_the_area_to_the_fix_source(fixes):
    truth, steps, scans = corridor_walk(seed=2, laps=1)
    before = fixes.restricted
    # the fuzzy KF searches near its estimate (lost_after=0: its box is never released)
    run("fkf", truth, steps, scans, fixes, initial=True, lost_after=0)
    assert fixes.restricted - before == len(scans)


def test_a_session_without_a_start_begins_at_its_first_fix_and_drops_earlier_steps(fixes):
    truth, steps, scans = corridor_walk(seed=3, laps=1)
    track, outcomes = run("ekf", truth, steps, scans, fixes, initial=False)
    first_scan_t = scans[0].t
    assert outcomes[0].estimates[0].source == "scan"
    assert len(track) == sum(s.t > first_scan_t for s in steps)
    assert np.hypot(outcomes[0].estimates[0].x - truth[2][0], outcomes[0].estimates[0].y - truth[2][1]) < 5.0


def test_scans_without_a_fix_are_skipped_with_the_reason_and_nothing_moves(fixes):
    est = SessionEstimator("kf", seed=1)
    est.start([0.0, 0.0], None, 0, [], None, "init")
    out = est.apply_batch([Step(1.0, 0.7, 90.0)], [Scan(2.0, {}), Scan(3.0, rss_at(1.0, 0.0))], fixes, SiteMap())
    assert [(n.index, n.reason) for n in out.skipped_scans] == [(0, "the scan heard nothing")]
    assert (out.applied_steps, out.applied_scans) == (1, 1)
    assert [e.source for e in out.estimates] == ["step", "scan"] and est.last_t == 3.0


def test_an_initial_position_without_a_time_takes_the_batchs_first_time(fixes):
    est = SessionEstimator("kf", seed=1)
    est.start([0.0, 0.0], None, 0, [], None, "init")
    out = est.apply_batch([], [Scan(5.0, {})], fixes, SiteMap())
    assert out.init_t == 5.0 and out.estimate is not None and out.estimate.t == 5.0
    assert est.apply_batch([Step(6.0, 0.7, 0.0)], [], fixes, SiteMap()).init_t is None


def test_inputs_older_than_the_last_applied_one_refuse_the_whole_batch(fixes):
    est = SessionEstimator("ekf", seed=1)
    est.start([0.0, 0.0], None, 0, [], None, "init")
    est.apply_batch([Step(10.0, 0.7, 0.0)], [], fixes, SiteMap())
    before = json.dumps(est.to_dict())
    with pytest.raises(LateInputs) as late:
        est.apply_batch([Step(11.0, 0.7, 0.0), Step(9.0, 0.7, 0.0)], [Scan(8.0, {})], fixes, SiteMap())
    assert [(i.kind, i.index) for i in late.value.items] == [("scan", 0), ("step", 1)]
    assert json.dumps(est.to_dict()) == before
