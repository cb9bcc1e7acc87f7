"""One walking session's estimator: a tracker plus floor hysteresis, landmark snaps and
beacon ranges, fed with steps and scans in time order. Plain data in and out
(``to_dict``/``from_dict``), so the server can store it after every batch and resume it
in any process. Fixes come from the caller (a callback), so this module knows nothing
about fingerprint models, HTTP or the database.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from server.estimation.tracking import (
    FloorTracker,
    LandmarkCorrector,
    apply_snap,
    make_tracker,
    range_and_std,
    tracker_from_dict,
)
from server.estimation.tracking.base import fix_cov
from server.estimation.types import Fix, Scan, Step

#: initial covariance (m²) when the phone gives a start position without one
DEFAULT_INITIAL_VAR_M2 = 1.0
STATE_VERSION = 1
#: innovation gate: a fix whose squared Mahalanobis distance from the estimate, under the
#: tracker's covariance plus the fix's, exceeds χ²(2 dof, 0.999) is an outlier (a fingerprint
#: match in the wrong place) and moves nothing
GATE_D2 = 13.82
#: after this many gated fixes in a row the tracker, not the fixes, may be lost: the next fix
#: is used whatever its distance
MAX_GATED_IN_A_ROW = 3


@dataclass(frozen=True)
class Beacon:
    """A transmitter with a known position; radio parameters make ranges possible."""

    id: str
    x: float
    y: float
    floor: int | None
    tx_power_dbm: float | None = None
    path_loss_exponent: float | None = None

    @property
    def ranged(self) -> bool:
        return self.tx_power_dbm is not None and self.path_loss_exponent is not None


def estimate(t: float | None, mean, cov, floor: int, source: str) -> dict[str, Any]:
    cov = np.asarray(cov, float)
    return {
        "t": None if t is None else float(t),
        "x": float(mean[0]),
        "y": float(mean[1]),
        "floor": int(floor),
        "covariance": [[float(cov[0, 0]), float(cov[0, 1])], [float(cov[1, 0]), float(cov[1, 1])]],
        "source": source,
    }


class SessionEstimator:
    """The whole per-session estimation state. ``tracker`` is None until the first fix
    of a session opened without an initial position."""

    def __init__(self, filter: str, seed: int):
        self.filter = filter
        self.seed = int(seed)
        self.tracker = None
        self.floors: FloorTracker | None = None
        self.landmarks = LandmarkCorrector({})
        self.last_t: float | None = None
        self.estimate: dict[str, Any] | None = None
        #: set (not stored) when the initial estimate, opened without a time, got one now
        self.init_t: float | None = None
        #: fixes refused by the innovation gate since the last accepted one
        self.gated_in_a_row = 0
        #: why the last scan's fix was refused (None: it was used); not stored
        self.rejected: str | None = None

    # -- starting -----------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self.tracker is not None

    def start(self, mean, cov, floor: int, walls, t: float | None, source: str) -> dict[str, Any]:
        cov = np.eye(2) * DEFAULT_INITIAL_VAR_M2 if cov is None else fix_cov(cov)
        self.tracker = make_tracker(self.filter, mean, cov, walls=walls, seed=self.seed)
        self.floors = FloorTracker(floor)
        return self._record(t, source)

    def _record(self, t: float | None, source: str) -> dict[str, Any]:
        self.estimate = estimate(t, self.tracker.mean, self.tracker.covariance, self.floors.floor, source)
        return self.estimate

    def search_region(self) -> tuple[float, float, float, float] | None:
        return self.tracker.search_region() if self.started else None

    # -- feeding ------------------------------------------------------------------
    def advance(self, t: float) -> None:
        """Note an input at time ``t`` (applied or skipped); an initial position given without
        a time takes the time of the first input."""
        if self.estimate is not None and self.estimate["source"] == "init" and self.estimate["t"] is None:
            self.estimate["t"] = float(t)
            self.init_t = float(t)
        self.last_t = t

    def step(self, step: Step) -> dict[str, Any] | None:
        """Predict with one step; None (step dropped) before the session has a position."""
        self.advance(step.t)
        if not self.started:
            return None
        self.tracker.predict(step)
        return self._record(step.t, "step")

    def scan(
        self,
        scan: Scan,
        fix: Fix,
        beacons: dict[str, Beacon],
        walls_of: Callable[[int], Any],
    ) -> dict[str, Any]:
        """Update with one scan's fix, beacon ranges and landmark snaps; start the session on
        its first fix. ``walls_of(level)`` gives a floor's walls when the floor changes.
        A fix that fails the innovation gate moves nothing (``rejected`` says why); the
        scan's beacon ranges and landmarks still apply."""
        self.advance(scan.t)
        self.rejected = None
        if not self.started:
            return self.start(fix.mean, fix.covariance, fix.floor, walls_of(fix.floor), scan.t, "scan")
        floor_before = self.floors.floor
        if self.floors.observe(fix.floor):
            # A confirmed floor change: walls of the new floor, restart from the fix there.
            self.tracker.set_walls(walls_of(self.floors.floor))
            self.tracker.reset(fix.mean, fix_cov(fix.covariance))
        elif fix.floor == floor_before:
            self._update(fix)
        # (a fix on another, not yet confirmed floor moves nothing)
        floor = self.floors.floor
        if self.tracker.supports_range:
            for tx_id, rss in scan.rss.items():
                b = beacons.get(tx_id)
                if b is not None and b.ranged and b.floor in (None, floor):
                    r, std = range_and_std(rss, b.tx_power_dbm, b.path_loss_exponent)
                    self.tracker.update_range((b.x, b.y), r, std)
        self.landmarks.beacons = {
            k: (b.x, b.y) for k, b in beacons.items() if k.startswith("ble:") and b.floor in (None, floor)
        }
        for snap in self.landmarks.observe(scan.rss)[:1]:
            apply_snap(self.tracker, snap)
        return self._record(scan.t, "scan")

    def _update(self, fix: Fix) -> None:
        """Update with the fix unless the innovation gate refuses it; after ``MAX_GATED_IN_A_ROW``
        refusals in a row the next fix is used anyway, so a lost tracker is pulled back."""
        R = fix_cov(fix.covariance)
        innovation = np.asarray(fix.mean, float) - np.asarray(self.tracker.mean, float)
        S = np.asarray(self.tracker.covariance, float) + R
        d2 = float(innovation @ np.linalg.solve(S, innovation))
        if d2 <= GATE_D2 or self.gated_in_a_row >= MAX_GATED_IN_A_ROW:
            self.gated_in_a_row = 0
            self.tracker.update(fix)
        else:
            self.gated_in_a_row += 1
            self.rejected = (f"fix {float(np.hypot(*innovation)):.1f} m from the estimate is an outlier "
                             f"(squared Mahalanobis distance {d2:.1f} > {GATE_D2})")

    # -- persistence ----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "version": STATE_VERSION,
            "filter": self.filter,
            "seed": self.seed,
            "tracker": None if self.tracker is None else self.tracker.to_dict(),
            "floors": None if self.floors is None else self.floors.to_dict(),
            "landmarks": self.landmarks.to_dict(),
            "last_t": self.last_t,
            "estimate": self.estimate,
            "gated_in_a_row": self.gated_in_a_row,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SessionEstimator:
        if d.get("version") != STATE_VERSION:
            raise ValueError(f"unsupported session state version {d.get('version')!r}")
        obj = cls(d["filter"], d["seed"])
        obj.tracker = None if d["tracker"] is None else tracker_from_dict(d["tracker"])
        obj.floors = None if d["floors"] is None else FloorTracker.from_dict(d["floors"])
        obj.landmarks = LandmarkCorrector.from_dict(d["landmarks"])
        obj.last_t = d["last_t"]
        obj.estimate = d["estimate"]
        obj.gated_in_a_row = d.get("gated_in_a_row", 0)  # absent from states stored before the gate
        return obj


def time_order(steps: list[Step], scans: list[Scan]) -> list[tuple[str, int, Step | Scan]]:
    """Steps and scans merged by time (stable; at equal times steps come first)."""
    items = [("step", i, s) for i, s in enumerate(steps)] + [("scan", i, s) for i, s in enumerate(scans)]
    items.sort(key=lambda it: (it[2].t, 0 if it[0] == "step" else 1, it[1]))
    return items


def multilateration_fix(
    rss: dict[str, float],
    beacons: dict[str, Beacon],
    floor_hint: int | None = None,
    default_r0_dbm: float = -45.0,
    default_gamma: float = 2.5,
    max_anchors: int = 8,
) -> Fix | None:
    """Least-squares multilateration from the heard transmitters with known positions
    (ranges by the path-loss model, each transmitter's own R0/γ where stored), on
    ``floor_hint`` or else the floor of the strongest heard transmitter that has one.
    None when no positioned transmitter is heard or the floor cannot be told."""
    from server.estimation.fingerprint import multilaterate
    from server.estimation.tracking import range_from_rss

    heard = sorted(((v, beacons[k]) for k, v in rss.items() if k in beacons), key=lambda vb: -vb[0])
    floor = floor_hint
    if floor is None:
        floor = next((b.floor for _, b in heard if b.floor is not None), None)
    anchors = [(v, b) for v, b in heard if b.floor in (None, floor)][:max_anchors]
    if floor is None or not anchors:
        return None
    xy = np.array([[b.x, b.y] for _, b in anchors])
    ranges = np.array([
        range_from_rss(v, default_r0_dbm if b.tx_power_dbm is None else b.tx_power_dbm,
                       default_gamma if b.path_loss_exponent is None else b.path_loss_exponent)
        for v, b in anchors
    ])
    mean, cov = multilaterate(xy, ranges)
    if not np.all(np.isfinite(mean)):
        return None
    return Fix(float(mean[0]), float(mean[1]), int(floor), fix_cov(cov))
