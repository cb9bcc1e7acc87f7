"""The PF's particle smoother (``tracking.particle_smoother``) and the session replay that serves
it (``estimation.replay``): descent through resamplings and resets, the lag-0 identity, the
covariance bound, and a replayed walk that reproduces the live one and is smoothed better."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from server.estimation.replay import RecordedBatch, RecordingFixes, replays, smoothed_by_replay
from server.estimation.session import SessionEstimator
from server.estimation.tracking import make_tracker
from server.estimation.tracking.particle_smoother import PathSmoother, no_wider
from server.estimation.types import Area, Fix, InitialHeading, NoFix, Scan, SiteMap, Step


def test_lineage_follows_a_resampling_and_a_reset():
    pf = make_tracker("pf-xy", [0.0, 0.0], np.eye(2), seed=3, n_particles=200)
    pf.take_lineage()  # from now on
    before = pf.particles.copy()
    pf.update(Fix(0.8, 0.0, 0, np.eye(2) * 0.05))  # a tight fix: the weights collapse and the cloud resamples
    rows = pf.take_lineage()
    assert not np.array_equal(rows, np.arange(len(rows)))
    np.testing.assert_array_equal(pf.particles, before[rows])
    assert np.array_equal(pf.take_lineage(), np.arange(len(pf.particles)))  # nothing since
    pf.reset([5.0, 5.0], np.eye(2))
    assert np.all(pf.take_lineage() == -1)


def test_the_live_tracker_keeps_no_lineage():
    pf = make_tracker("pf", [0.0, 0.0], np.eye(2), seed=3, n_particles=200)
    pf.update(Fix(0.8, 0.0, 0, np.eye(2) * 0.05))
    assert pf.lineage is None


def test_no_wider_bounds_every_direction_and_keeps_a_narrower_covariance():
    bound = np.array([[4.0, 1.0], [1.0, 2.0]])
    wide = np.array([[1.0, 0.0], [0.0, 9.0]])
    out = no_wider(wide, bound)
    assert np.linalg.eigvalsh(bound - out).min() > -1e-8
    assert np.linalg.eigvalsh(wide - out).min() > -1e-8
    narrow = 0.3 * bound
    np.testing.assert_allclose(no_wider(narrow, bound), narrow, atol=1e-8)


def _walk(n_steps: int = 120, scan_every: int = 4, seed: int = 5):
    """A walk east along y = 0 whose steps say 6° left and 8 % long, a fix (σ 1.2 m) every few
    steps; the steps, scans, fixes by scan time and the truth by input time."""
    rng = np.random.default_rng(seed)
    steps, scans, fixes, truth = [], [], {}, {}
    for i in range(n_steps):
        t = 0.5 * (i + 1)
        x = 0.7 * (i + 1)
        truth[t] = (x, 0.0)
        steps.append(Step(t, 0.7 * 1.08 + rng.normal(0, 0.03), 90.0 - 6.0 + rng.normal(0, 2.0)))
        if (i + 1) % scan_every == 0:
            ts = t + 0.25
            truth[ts] = (x, 0.0)
            scans.append(Scan(ts, {"wifi:a": -60.0}))
            fixes[ts] = (x + rng.normal(0, 1.2), rng.normal(0, 1.2))
    return steps, scans, fixes, truth


class _Fixes:
    def __init__(self, by_t, every_nth_none: int = 7):
        self.by_t, self.every = by_t, every_nth_none
        self.asked = 0

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        self.asked += 1
        if self.asked % self.every == 0:
            raise NoFix("nothing heard")  # some scans give none: recorded as such
        x, y = self.by_t[scan.t]
        return Fix(x, y, 0, np.eye(2) * 1.44, shared_share=None)


def _live(filter: str = "pf", batch: int = 10, start: bool = True, grids: dict | None = None,
          heading: InitialHeading | None = None):
    """The walk as the server runs it: opened with a start (``start``; else on its first fix; with
    ``heading``, its direction there), each batch from the stored (JSON) state; the site's survey
    grid ``grids`` (none by default)."""
    steps, scans, fixes, truth = _walk()
    est = SessionEstimator(filter, seed=11)
    track = [est.start([0.0, 0.0], None, 0, [], None, "init", heading=heading)] if start else []
    opening = json.loads(json.dumps(est.to_dict()))
    source, site, recorded = _Fixes(fixes), SiteMap(grids=dict(grids or {})), []
    for k in range(0, len(steps), batch):
        t0, t1 = steps[k].t, steps[min(k + batch, len(steps)) - 1].t + 0.4
        bs, bc = steps[k:k + batch], [s for s in scans if t0 <= s.t < t1]
        est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        recording = RecordingFixes(source)
        track += est.apply_batch(bs, bc, recording, site).estimates
        recorded.append(RecordedBatch.from_dict(json.loads(json.dumps(
            recording.batch(bs, bc, dict(site.grids)).to_dict()))))
    if start:
        track[0] = replace(track[0], t=steps[0].t)  # (the server dates the start with the first input)
    return opening, recorded, site, track, truth


def _error(track, truth) -> float:
    return float(np.mean([math.dist((e.x, e.y), truth.get(e.t, (0.0, 0.0))) for e in track]))


def test_a_replayed_pf_session_reproduces_its_track_and_smooths_it():
    opening, batches, site, track, truth = _live()
    smoothed = smoothed_by_replay(opening, batches, site, track)
    assert smoothed is not None
    assert [(e.t, e.source, e.floor) for e in smoothed] == [(e.t, e.source, e.floor) for e in track]
    live_err, smooth_err = _error(track, truth), _error(smoothed, truth)
    print(f"mean error: live {live_err:.2f} m, particle-smoothed {smooth_err:.2f} m")
    assert smooth_err < 0.9 * live_err
    for a, b in zip(track, smoothed, strict=True):  # never wider than live
        assert np.linalg.eigvalsh(np.array(a.covariance) - np.array(b.covariance)).min() > -1e-6


def test_a_session_told_its_start_direction_is_replayed_with_it():
    """The start direction waits in the opening state, so the replay takes it at the same step."""
    opening, batches, site, track, _ = _live(heading=InitialHeading(90.0, 5.0))
    assert opening["initial_heading"] == [90.0, 5.0]
    assert smoothed_by_replay(opening, batches, site, track) is not None  # (None: the replay drew otherwise)
    _, _, _, untold, _ = _live()
    assert [(e.x, e.y) for e in track] != [(e.x, e.y) for e in untold]


def test_a_session_started_on_its_first_fix_is_replayed_too():
    opening, batches, site, track, truth = _live(start=False)
    assert opening["tracker"] is None and track[0].source == "scan"
    smoothed = smoothed_by_replay(opening, batches, site, track)
    assert smoothed is not None and len(smoothed) == len(track)
    assert _error(smoothed, truth) < _error(track, truth)


def test_a_cloud_drawn_anew_ends_the_paths_before_it():
    """The estimates before a reset are smoothed by the last cloud before it, not by the new one."""
    pf = make_tracker("pf-xy", [0.0, 0.0], np.eye(2), seed=3, n_particles=300)
    smoother = PathSmoother(lag=10)
    smoother.observe(pf, pf.covariance)
    pf.predict(Step(0.5, 0.7, 90.0))
    pf.update(Fix(0.9, 0.0, 0, np.eye(2) * 0.2))
    smoother.observe(pf, pf.covariance)
    before = pf.mean.copy()
    pf.reset([30.0, 30.0], np.eye(2))
    smoother.observe(pf, pf.covariance)
    out = smoother.finish()
    assert len(out) == 3
    np.testing.assert_allclose(out[1].mean, before, atol=1e-9)  # its own cloud, the last before the reset
    assert math.dist(out[0].mean, (30.0, 30.0)) > 20 and math.dist(out[2].mean, (30.0, 30.0)) < 3


def test_the_replay_uses_the_survey_grid_each_batch_had():
    """The survey's grid comes from the site's active model, so a retrain may move it after the walk:
    the replay takes the grid each batch recorded, and without it (a record that lacks it) the
    moved grid makes the PF weigh its heading runs differently and the replay no longer reproduces."""
    opening, batches, _, track, _ = _live(grids={(0, 0): 0.0})
    assert all(b.grids == {(0, 0): 0.0} for b in batches)
    retrained = SiteMap(grids={(0, 0): 20.0})
    assert smoothed_by_replay(opening, batches, retrained, track) is not None
    assert smoothed_by_replay(opening, [replace(b, grids=None) for b in batches], retrained, track) is None


def test_a_replay_that_does_not_reproduce_the_track_gives_none():
    opening, batches, site, track, _ = _live()
    assert smoothed_by_replay(opening, batches[:-1], site, track) is None  # a batch missing
    moved = list(track)
    moved[30] = replace(moved[30], x=moved[30].x + 0.01)
    assert smoothed_by_replay(opening, batches, site, moved) is None  # a stored estimate that differs
    k = next(i for i, b in enumerate(batches) if any(isinstance(f, Fix) for f in b.fixes))
    answers = [replace(f, x=f.x + 3.0) if isinstance(f, Fix) else f for f in batches[k].fixes]
    tampered = [*batches[:k], replace(batches[k], fixes=tuple(answers)), *batches[k + 1:]]
    assert smoothed_by_replay(opening, tampered, site, track) is None  # another fix than live
    short = [*batches[:k], replace(batches[k], fixes=batches[k].fixes[:-1]), *batches[k + 1:]]
    assert smoothed_by_replay(opening, short, site, track) is None  # fewer answers than asked


def test_lag_zero_gives_the_live_estimates_back():
    """With no look-ahead each estimate is its own cloud: the live mean and covariance."""
    opening, batches, site, track, _ = _live()
    smoothed = smoothed_by_replay(opening, batches, site, track, lag=0)
    assert smoothed is not None
    for a, b in zip(track, smoothed, strict=True):
        assert math.isclose(a.x, b.x, abs_tol=1e-9) and math.isclose(a.y, b.y, abs_tol=1e-9)
        np.testing.assert_allclose(b.covariance, a.covariance, atol=1e-6)


@pytest.mark.parametrize("filter, expected", [("pf", True), ("pf-xy", True), ("skpf", False), ("ekf", False),
                                              ("kf", False), ("nope", False)])
def test_which_filters_are_smoothed_by_replay(filter, expected):
    assert replays(filter) is expected


def test_the_path_smoother_rejects_a_negative_lag():
    with pytest.raises(ValueError):
        PathSmoother(-1)


def test_a_recorded_batch_survives_json():
    batch = RecordedBatch((Step(1.0, 0.7, 90.0),), (Scan(1.2, {"ble:x": -70.0}, 45.0),),
                          (Fix(1.0, 2.0, 1, np.diag([2.0, 3.0]), building=2, shared_share=0.4), "nothing heard"),
                          {(2, 1): 12.5})
    back = RecordedBatch.from_dict(json.loads(json.dumps(batch.to_dict())))
    assert back.steps == batch.steps and back.scans == batch.scans and back.fixes[1] == "nothing heard"
    assert back.grids == {(2, 1): 12.5}
    assert RecordedBatch.from_dict({**batch.to_dict(), "grids": None}).grids is None
    f = back.fixes[0]
    assert isinstance(f, Fix) and (f.x, f.y, f.floor, f.building, f.shared_share) == (1.0, 2.0, 1, 2, 0.4)
    np.testing.assert_array_equal(f.covariance, np.diag([2.0, 3.0]))
