"""Landmark correction with hysteresis on iBeacon RSS.

Per beacon: raw RSS → Tukey outlier filter over the last ``window`` (10) samples →
scalar Kalman filter (random-walk RSS, Q = 0.015, R = 1.5) → hysteresis zone.
The position snaps to a beacon when its filtered RSS enters the strong zone
(> −52 dBm) and may snap to it again only after the filtered RSS has left the zone
(< −65 dBm). The corrector returns ``Snap`` events; applying them to a tracker is
``tracker.reset(snap.position, snap.covariance)`` (see ``apply_snap``).
"""

from __future__ import annotations

import statistics
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np


class TukeyFilter:
    """Rejects a sample outside [Q1 − k·IQR, Q3 + k·IQR] of the previous samples.

    Every sample (also a rejected one) enters the window, so a lasting change of
    level is accepted after a few samples. The IQR has a floor (``min_iqr``) so that a
    run of near-identical readings does not reject ordinary RSS noise (dB).
    """

    def __init__(self, window: int = 10, k: float = 1.5, min_samples: int = 5, min_iqr: float = 3.0):
        self.window = int(window)
        self.k = float(k)
        self.min_samples = int(min_samples)
        self.min_iqr = float(min_iqr)
        self.samples: deque[float] = deque(maxlen=self.window)

    def accept(self, value: float) -> bool:
        ok = True
        if len(self.samples) >= self.min_samples:
            # numpy's default (linear) quartiles, at a twentieth of np.percentile's cost on 10 values
            q1, _, q3 = statistics.quantiles(self.samples, n=4, method="inclusive")
            iqr = max(q3 - q1, self.min_iqr)
            ok = (q1 - self.k * iqr) <= value <= (q3 + self.k * iqr)
        self.samples.append(float(value))
        return bool(ok)

    def to_dict(self) -> dict[str, Any]:
        return {"window": self.window, "k": self.k, "min_samples": self.min_samples, "min_iqr": self.min_iqr,
                "samples": list(self.samples)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TukeyFilter:
        obj = cls(d["window"], d["k"], d["min_samples"], d["min_iqr"])
        obj.samples.extend(float(v) for v in d["samples"])
        return obj


class ScalarKalman:
    """x_k = x_{k−1} + w (var Q), z_k = x_k + v (var R)."""

    def __init__(self, q: float = 0.015, r: float = 1.5):
        self.q, self.r = float(q), float(r)
        self.x: float | None = None
        self.p = float(r)

    def update(self, z: float) -> float:
        if self.x is None:
            self.x, self.p = float(z), self.r
            return self.x
        p = self.p + self.q
        k = p / (p + self.r)
        self.x = self.x + k * (float(z) - self.x)
        self.p = (1.0 - k) * p
        return self.x

    def to_dict(self) -> dict[str, Any]:
        return {"q": self.q, "r": self.r, "x": self.x, "p": self.p}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ScalarKalman:
        obj = cls(d["q"], d["r"])
        obj.x, obj.p = d["x"], float(d["p"])
        return obj


@dataclass(frozen=True)
class Snap:
    beacon_id: str
    x: float
    y: float
    rss_dbm: float  # filtered
    std_m: float

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y])

    @property
    def covariance(self) -> np.ndarray:
        return np.eye(2) * self.std_m**2


class LandmarkCorrector:
    """Tracks the iBeacons with known positions (``beacons``: id → (x, y))."""

    def __init__(
        self,
        beacons: dict[str, Any],
        enter_dbm: float = -52.0,
        leave_dbm: float = -65.0,
        window: int = 10,
        q: float = 0.015,
        r: float = 1.5,
        snap_std_m: float = 1.0,
    ):
        if leave_dbm >= enter_dbm:
            raise ValueError("leave_dbm must be below enter_dbm (hysteresis)")
        self.beacons = {str(k): (float(v[0]), float(v[1])) for k, v in beacons.items()}
        self.enter_dbm, self.leave_dbm = float(enter_dbm), float(leave_dbm)
        self.window, self.q, self.r, self.snap_std_m = int(window), float(q), float(r), float(snap_std_m)
        self.tukey: dict[str, TukeyFilter] = {}
        self.kalman: dict[str, ScalarKalman] = {}
        self.armed: dict[str, bool] = {}

    def filtered_rss(self, beacon_id: str) -> float | None:
        kf = self.kalman.get(beacon_id)
        return None if kf is None else kf.x

    def observe(self, rss: dict[str, float]) -> list[Snap]:
        """Feed one scan; returns the snaps it triggers, strongest first."""
        snaps = []
        for tx_id, value in rss.items():
            if tx_id not in self.beacons:
                continue
            tukey = self.tukey.setdefault(tx_id, TukeyFilter(self.window))
            if not tukey.accept(value):
                continue
            level = self.kalman.setdefault(tx_id, ScalarKalman(self.q, self.r)).update(value)
            armed = self.armed.get(tx_id, True)
            if armed and level > self.enter_dbm:
                x, y = self.beacons[tx_id]
                snaps.append(Snap(tx_id, x, y, level, self.snap_std_m))
                self.armed[tx_id] = False
            elif not armed and level < self.leave_dbm:
                self.armed[tx_id] = True
        return sorted(snaps, key=lambda s: -s.rss_dbm)

    def to_dict(self) -> dict[str, Any]:
        return {
            "beacons": {k: list(v) for k, v in self.beacons.items()},
            "enter_dbm": self.enter_dbm,
            "leave_dbm": self.leave_dbm,
            "window": self.window,
            "q": self.q,
            "r": self.r,
            "snap_std_m": self.snap_std_m,
            "tukey": {k: v.to_dict() for k, v in self.tukey.items()},
            "kalman": {k: v.to_dict() for k, v in self.kalman.items()},
            "armed": dict(self.armed),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LandmarkCorrector:
        obj = cls(d["beacons"], d["enter_dbm"], d["leave_dbm"], d["window"], d["q"], d["r"], d["snap_std_m"])
        obj.tukey = {k: TukeyFilter.from_dict(v) for k, v in d["tukey"].items()}
        obj.kalman = {k: ScalarKalman.from_dict(v) for k, v in d["kalman"].items()}
        obj.armed = {k: bool(v) for k, v in d["armed"].items()}
        return obj


def apply_snap(tracker, snap: Snap) -> None:
    """Move a tracker onto the beacon: restart it from N(beacon, snap_std²·I)."""
    tracker.reset(snap.position, snap.covariance)
