"""A particle-filter session replayed from what it was given: its smoothed track.

The stored track of a PF session holds each estimate's mean and covariance, not its particles,
and smoothing a cloud's moments (the RTS of ``tracking.smoother``) discards the shape the walls
and the fixes gave it. The particles can be had again: the PF is deterministic given its stored
generator, so a session opened from its opening state (``SessionEstimator.to_dict`` right after
``open``) and fed its batches' steps and scans again, each scan answered by the fix it got live
(``RecordedBatch``: the model may have been retrained since), repeats the live filter exactly.
``smoothed_by_replay`` does that with a ``PathSmoother`` following the particles, checks that
the replay reproduces the stored track estimate for estimate, and returns the path-space smoothed
track — or None when it does not reproduce (the site's plan, transmitters or the PF's draws changed
since; the survey's grid, which a retrain may move, is recorded with each batch), and
the caller says so (the server: 409, while the RTS over the stored moments still smooths it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from server.estimation.session import FixSource, SessionEstimator
from server.estimation.tracking.base import TRACKERS, Tracker
from server.estimation.tracking.particle_smoother import DEFAULT_LAG, PathSmoother
from server.estimation.tracking.pf import ParticleFilterXYTracker
from server.estimation.types import Area, Estimate, Fix, NoFix, Scan, SiteMap, Step, TrackerFailure

#: a replayed estimate reproduces a stored one when its position is within this (m) of it
SAME_M = 1e-6


def replays(filter: str) -> bool:
    """Whether a session of this filter is smoothed by replay (so its inputs are worth keeping)."""
    cls = TRACKERS.get(filter)
    return cls is not None and issubclass(cls, ParticleFilterXYTracker)


@dataclass(frozen=True)
class RecordedBatch:
    """One applied batch as the tracker saw it: its steps and scans, the fix source's answers in the
    order it was asked (a ``Fix``, or why it gave none), and the survey's grid directions by
    (building, level) that the site had then (``SiteMap.grids``: they come from the active model, so
    a retrain may move them; None: not recorded, the site's current ones apply)."""

    steps: tuple[Step, ...]
    scans: tuple[Scan, ...]
    fixes: tuple[Fix | str, ...]
    grids: dict[tuple[int, int], float] | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"steps": [asdict(s) for s in self.steps], "scans": [asdict(s) for s in self.scans],
                               "fixes": [_fix_dict(f) for f in self.fixes]}
        if self.grids is not None:
            out["grids"] = [[b, level, deg] for (b, level), deg in self.grids.items()]
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RecordedBatch:
        grids = d.get("grids")
        return cls(tuple(Step(**s) for s in d["steps"]), tuple(Scan(**s) for s in d["scans"]),
                   tuple(_fix_of(f) for f in d["fixes"]),
                   None if grids is None else {(int(b), int(level)): float(deg) for b, level, deg in grids})


def _fix_dict(f: Fix | str) -> dict[str, Any]:
    if isinstance(f, str):
        return {"none": f}
    return {"x": f.x, "y": f.y, "floor": f.floor, "building": f.building, "share": f.shared_share,
            "cov": np.asarray(f.covariance, float).tolist()}


def _fix_of(d: dict[str, Any]) -> Fix | str:
    if "none" in d:
        return str(d["none"])
    return Fix(float(d["x"]), float(d["y"]), int(d["floor"]), np.asarray(d["cov"], float), building=int(d["building"]),
               shared_share=None if d["share"] is None else float(d["share"]))


class RecordingFixes:
    """A ``FixSource`` that keeps what ``source`` answered, in order (``answers``)."""

    def __init__(self, source: FixSource):
        self.source = source
        self.answers: list[Fix | str] = []

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        try:
            f = self.source.fix(scan, near)
        except NoFix as why:
            self.answers.append(str(why))
            raise
        self.answers.append(f)
        return f

    def batch(self, steps: Sequence[Step], scans: Sequence[Scan],
              grids: dict[tuple[int, int], float] | None = None) -> RecordedBatch:
        """The batch just applied with these answers, as ``smoothed_by_replay`` replays it."""
        return RecordedBatch(tuple(steps), tuple(scans), tuple(self.answers), grids)


class _NotReproduced(Exception):
    """The replay asked for more fixes than were recorded."""


class _Recorded:
    """The recorded answers again, in order."""

    def __init__(self, answers: Sequence[Fix | str]):
        self._answers = iter(answers)

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        answer = next(self._answers, None)
        if answer is None:
            raise _NotReproduced
        if isinstance(answer, str):
            raise NoFix(answer)
        return answer


def smoothed_by_replay(opening: dict[str, Any], batches: Sequence[RecordedBatch], site: SiteMap,
                       track: Sequence[Estimate], lag: int = DEFAULT_LAG) -> list[Estimate] | None:
    """The stored ``track`` of a PF session path-space smoothed (same times, floors and sources),
    by replaying its ``batches`` from its ``opening`` state on ``site``; None when the replay does
    not reproduce the track (then nothing here can be trusted)."""
    smoother = PathSmoother(lag)

    def observe(tracker: Tracker, estimate: Estimate, own: np.ndarray) -> None:
        if not isinstance(tracker, ParticleFilterXYTracker):
            raise _NotReproduced
        smoother.observe(tracker, own, np.asarray(estimate.covariance, float) - own)

    try:
        est = SessionEstimator.from_dict(opening)
        replayed: list[Estimate] = []
        if est.estimate is not None and est.tracker is not None:  # the given start
            replayed.append(est.estimate)
            observe(est.tracker, est.estimate, np.asarray(est.estimate.covariance, float))
        for batch in batches:
            est = SessionEstimator.from_dict(est.to_dict())  # as live: each batch from the stored state
            est.on_record = observe
            as_then = site if batch.grids is None else replace(site, grids=batch.grids)
            outcome = est.apply_batch(list(batch.steps), list(batch.scans), _Recorded(batch.fixes), as_then)
            replayed.extend(outcome.estimates)
    except (_NotReproduced, TrackerFailure, ValueError, KeyError, TypeError):
        return None
    if not _reproduces(replayed, track):
        return None
    return [Estimate.of(e.t, s.mean, s.covariance, e.floor, e.source, e.building)
            for e, s in zip(track, smoother.finish(), strict=True)]


def _reproduces(replayed: Sequence[Estimate], track: Sequence[Estimate]) -> bool:
    """Same length, and each replayed estimate the stored one (the initial one's time is the first
    input's, set after it was stored)."""
    return len(replayed) == len(track) and all(
        (a.source, a.floor, a.building) == (b.source, b.floor, b.building)
        and (a.source == "init" or a.t == b.t)
        and abs(a.x - b.x) <= SAME_M and abs(a.y - b.y) <= SAME_M
        for a, b in zip(replayed, track, strict=True)
    )
