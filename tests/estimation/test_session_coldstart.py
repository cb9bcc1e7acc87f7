"""A session opened without a position starts on its first fix (``SessionEstimator.scan``). A
fingerprint model's covariance can span the floor (its posterior's far candidates: σ ≈ 40 m on
the MSFT walks, whose fixes are ≈ 14 m off): the self-calibrating trackers then start no wider
than ``COLD_START_MAX_STD_M`` and trust their fixes from a lower prior scale, every other start from
a fix (a seed form's, a restart on a confirmed floor change) no wider than ``START_MAX_STD_M``, and a
search box waits until the tracker is localised within it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from server.estimation.floorplan import Walkable
from server.estimation.session import (
    COLD_FIX_SCALE_PRIOR,
    COLD_START_MAX_STD_M,
    START_MAX_STD_M,
    SessionEstimator,
    cold_start_cov,
)
from server.estimation.tracking import tracker_names
from server.estimation.tracking.fixnoise import FixNoiseScale
from server.estimation.types import Beacon, Fix, Scan, SiteMap, Step

#: 100 × 10 m corridor along x
CORRIDOR = SiteMap(walkable={(0, 0): Walkable([[(0, 0), (100, 0), (100, 10), (0, 10)]])})


class Table:
    """Fixes by scan time."""

    def __init__(self, fixes: dict[float, Fix]):
        self.fixes = fixes

    def fix(self, scan, near):
        return self.fixes[scan.t]


def corridor_walk(seed: int, sigma_model_m: float = 40.0):
    """30 s east along the corridor from (10, 5): a step every 0.5 s, a fix every 2 s, the
    fixes 3 m off (σ) while the model says ``sigma_model_m``. Returns the inputs and the truth."""
    rng = np.random.default_rng(seed)
    steps, scans, fixes, truth = [], [], {}, {}
    for k in range(60):
        t = 0.5 * (k + 1)
        steps.append(Step(t, 0.7, 90.0, length_std_m=0.05, heading_std_deg=3.0))
        truth[t] = (10.0 + 0.7 * (k + 1), 5.0)
        if k % 4 == 0:
            ts, x = (0.1, 10.0) if k == 0 else (t + 0.1, 10.0 + 0.7 * (k + 1))
            off = np.zeros(2) if k == 0 else rng.normal(0.0, 3.0, 2)
            fixes[ts] = Fix(x + off[0], 5.0 + off[1], 0, np.eye(2) * sigma_model_m**2)
            scans.append(Scan(ts, {}))
            truth[ts] = (x, 5.0)
    return steps, scans, Table(fixes), truth


def test_the_start_covariance_is_capped_along_its_own_axes():
    c, s = np.cos(0.3), np.sin(0.3)
    axes = np.array([[c, -s], [s, c]])
    wide = axes @ np.diag([40.0**2, 4.0**2]) @ axes.T
    capped = cold_start_cov(wide)
    w, v = np.linalg.eigh(capped)
    assert w == pytest.approx([4.0**2, COLD_START_MAX_STD_M**2])
    assert abs(v[:, 1] @ axes[:, 0]) == pytest.approx(1.0)  # the long axis kept
    small = np.array([[9.0, 1.0], [1.0, 4.0]])
    assert np.allclose(cold_start_cov(small), small)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_pf_started_on_a_wide_fix_in_a_corridor_starts_at_the_fix(seed):
    """Without the cap the start cloud (σ 40 m) clipped to the corridor has its mean ≈ 24 m
    east of the fix after the first step, and the σ 40 m fixes pull it back slowly: the first
    10 s were 12.5–14.8 m off on these seeds, 3.6–4.3 m with the cap."""
    steps, scans, fixes, truth = corridor_walk(seed)
    est = SessionEstimator("pf", seed=seed)
    track = []
    for k in range(0, 60, 4):  # 2 s batches, the state stored and loaded between them
        est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        batch = [s for s in scans if 0.5 * k < s.t <= 0.5 * (k + 4)]
        track += est.apply_batch(steps[k:k + 4], batch, fixes, CORRIDOR).estimates
    errors = [np.hypot(e.x - truth[e.t][0], e.y - truth[e.t][1]) for e in track]
    assert np.mean(errors[:20]) < 6.0
    assert np.mean(errors[20:]) < 4.0


@pytest.mark.parametrize("name", ["pf", "skpf", "ekf", "ukf"])
def test_a_self_calibrating_session_started_on_a_fix_starts_narrower_and_trusts_its_fixes_more(name):
    est = SessionEstimator(name, seed=1)
    fix = Fix(10.0, 5.0, 0, np.eye(2) * 40.0**2)
    est.scan(Scan(0.0, {}), fix, SiteMap())
    assert est.tracker is not None
    assert np.sqrt(np.linalg.eigvalsh(est.tracker.covariance)[-1]) < 1.3 * COLD_START_MAX_STD_M
    assert est.fix_noise.scale == pytest.approx(COLD_FIX_SCALE_PRIOR)
    resumed = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
    assert resumed.fix_noise.scale == pytest.approx(COLD_FIX_SCALE_PRIOR)
    known = SessionEstimator(name, seed=1)
    known.start([10.0, 5.0], None, 0, [], None, "init")
    assert known.fix_noise.scale == 1.0


@pytest.mark.parametrize("name", ["kf", "fkf", "pf-xy", "skpf-xy"])
def test_a_seed_form_starts_on_the_fix_as_the_model_gives_it(name):
    est = SessionEstimator(name, seed=1)
    est.scan(Scan(0.0, {}), Fix(10.0, 5.0, 0, np.eye(2) * 40.0**2), SiteMap())
    assert est.tracker is not None
    assert np.sqrt(np.linalg.eigvalsh(est.tracker.covariance)[-1]) > 30.0
    assert est.fix_noise.scale == 1.0


#: Fixes of the path-loss model from transmitters nearly in a line (multi-floor crowd scenario,
#: seed 5): σ ≈ 10⁵–10⁶ m across the line, the covariance nearly singular, the means ≈ 2 m apart.
DEGENERATE = [Fix(29.4, -0.4, 1, np.array([[7.39e10, 3.17e10], [3.17e10, 1.36e10]])),
              Fix(28.8, 1.2, 1, np.array([[4.49e11, 1.926e11], [1.926e11, 8.254e10]])),
              Fix(28.6, 1.6, 1, np.array([[2.335e11, 1.001e11], [1.001e11, 4.29e10]]))]


def _walk_on_degenerate_fixes(est: SessionEstimator, first_t: float = 0.0) -> list:
    out = []
    for i in range(6):
        t = first_t + 2.0 * i
        est.step(Step(t, 0.7, 180.0))
        out.append(est.scan(Scan(t + 0.5, {"wifi:x": -50.0}), DEGENERATE[i % 3], SiteMap()).estimate)
    return out


@pytest.mark.parametrize("name", tracker_names())
def test_degenerate_fixes_at_a_cold_start_or_a_floor_change_keep_the_track_on_the_site(name):
    """A tracker (re)started on such a fix with its covariance as given went 5–400 km away on its
    next fixes (the multi-floor crowd benchmark's round 1: a 519 m mean) or raised (ukf-xy); every
    start from a fix, the first one or a confirmed floor change, is capped (``START_MAX_STD_M``)."""
    cold = SessionEstimator(name, seed=3)
    track = _walk_on_degenerate_fixes(cold)
    moved = SessionEstimator(name, seed=3)
    moved.start([20.0, 10.0], np.eye(2), 0, [], None, "init")
    after = [e for e in _walk_on_degenerate_fixes(moved) if e.floor == 1]
    assert len(after) >= 3  # the floor change confirmed, then fixes on the new floor
    for e in track + after:  # (across the transmitters' line the fixes say nothing: within 2σ of the cap)
        assert np.hypot(e.x - 28.8, e.y - 1.2) < 2 * START_MAX_STD_M
        assert np.all(np.isfinite(e.covariance))  # (the reported one keeps what the cap left out: honest, wide)
    for est in (cold, moved):
        assert est.tracker is not None and np.linalg.eigvalsh(est.tracker.covariance)[-1] < 1.5 * START_MAX_STD_M**2


@pytest.mark.parametrize(("name", "placed"), [("ekf", True), ("pf", True), ("ukf", False)])
def test_ranges_that_place_the_walker_shrink_what_a_degenerate_start_left_in_the_report(name, placed):
    """Started on such a fix, the tracker is capped at 15 m but the report keeps the fix's 10⁵ m
    across the transmitters' line as the start's excess. Beacons heard at known ranges then place
    the walker within a metre: the reported covariance follows the tracker's down (left out of the
    excess, it stayed at σ ≈ 300 m, and on the multi-floor crowd benchmark's ground floor no
    estimate ever passed the crowd gate). The ukf, whose sigma points lie ±30 m out where every one
    sees nearly the same log-range, takes almost nothing from ranges this close: its report keeps the
    excess as its own covariance keeps its width (the excess goes as the tracker's own, never faster)."""
    beacons = {f"ble:{i}": Beacon(f"ble:{i}", x, y, 1, -59.0, 2.0) for i, (x, y) in
               enumerate([(27.5, 0.0), (30.5, 2.5), (29.0, -1.5), (27.0, 2.5)])}  # (ranges under 3 m)
    truth = np.array([29.0, 1.0])
    rss = {k: -59.0 - 20.0 * math.log10(math.hypot(*(truth - (b.x, b.y)))) for k, b in beacons.items()}
    est = SessionEstimator(name, seed=3)
    site = SiteMap(beacons=beacons)
    est.scan(Scan(0.0, {}), DEGENERATE[0], site)  # (no beacon heard yet)
    first = est.step(Step(0.2, 0.01, 0.0))
    assert first is not None and np.trace(first.covariance) > 1e4  # the start's excess: honest, wide
    for i in range(1, 8):
        last = est.scan(Scan(0.5 * i, rss), DEGENERATE[i % 3], site).estimate
    assert est.tracker is not None
    own = float(np.trace(np.asarray(est.tracker.covariance)[:2, :2]))
    reported = float(np.trace(last.covariance))
    assert own <= reported
    if placed:
        assert own < 5.0 and reported < 2.0  # (within the crowd gate's trace, from 10⁶ m²)
        assert np.hypot(last.x - truth[0], last.y - truth[1]) < 3.0
    else:
        assert own > 100.0 and reported > 1e3


def test_the_search_box_waits_until_the_tracker_is_localised_within_it():
    """The fkf's ±9 m box around a cold start 40 m wide would keep every later fix near a
    possibly wrong first one (MSFT folds 0–1: 11.2 m cold with the box from the start, 10.2 m
    without)."""
    cold = SessionEstimator("fkf", seed=1)
    cold.scan(Scan(0.0, {}), Fix(10.0, 5.0, 0, np.eye(2) * 40.0**2), SiteMap())
    assert cold.search_area() is None
    known = SessionEstimator("fkf", seed=1)
    known.start([10.0, 5.0], None, 0, [], None, "init")
    area = known.search_area()
    assert area is not None and (area.x, area.y) == pytest.approx((10.0, 5.0))


def test_the_fix_noise_prior_round_trips_and_an_older_pair_reads_at_prior_one():
    s = FixNoiseScale(prior=0.25)
    assert s.scale == pytest.approx(0.25)
    s.observe(np.array([3.0, 0.0]), np.eye(2), np.eye(2) * 4.0)
    assert FixNoiseScale.from_list(json.loads(json.dumps(s.to_list()))) == s
    assert FixNoiseScale.from_list([0.0, 0.0]).prior == 1.0
    assert FixNoiseScale().to_list() == [0.0, 0.0]  # the stored form of a known-start session is unchanged


@pytest.mark.parametrize("name", tracker_names())
def test_a_fix_degenerate_beyond_working_precision_updates_without_raising(name):
    """A path-loss fix logged in the multi-floor crowd benchmark (seed 4): 10¹⁷ m² across the transmitters'
    line and rank one to working precision. Taken as R it made P + R singular and every filter raised (a
    500 for that batch on every retry); ``fix_cov`` bounds its variance at ``MAX_FIX_VAR_M2``."""
    R = np.array([[1.714108329735443e17, -3.166785238423323e17], [-3.166785238423323e17, 5.850580486849203e17]])
    est = SessionEstimator(name, seed=1)
    est.scan(Scan(0.0, {}), Fix(10.0, 10.0, 0, np.eye(2) * 9.0), SiteMap())
    for k in range(8):
        est.step(Step(0.5 * k + 0.5, 0.7, 90.0))
        if k % 2 == 1:
            est.scan(Scan(0.5 * k + 0.6, {}), Fix(10.0 + 0.7 * (k + 1), 10.0, 0, np.eye(2) * 9.0), SiteMap())
    e = est.scan(Scan(5.0, {}), Fix(12.0, 10.0, 0, R), SiteMap()).estimate
    assert np.hypot(e.x - 15.6, e.y - 10.0) < 5.0 and np.all(np.isfinite(e.covariance))
