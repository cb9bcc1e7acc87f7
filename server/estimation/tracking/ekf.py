"""EKF: heading and step length uncertain; fix or beacon-range measurements.

Prediction: x⁻ = x + f(d, h), P⁻ = P + J·diag(σd², σh²)·Jᵀ + q·I, with J the motion
Jacobian ∂f/∂(d, h) (see ``motion``).
Updates:
- ``update(fix)``: z = fix mean, H = I, R = fix.covariance (the fingerprint model's
  adaptive covariance).
- ``update_range(beacon, r, σr, on_wall)``: h(x) = ‖x − beacon‖, H = (x − b)ᵀ/‖x − b‖,
  used only when the measured range is within ``max_range_m`` (3 m) of the beacon;
  when the beacon sits on a wall the posterior mean is kept on the wall's side.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from server.estimation.tracking.base import Tracker, as_cov, as_mean, fix_cov, register
from server.estimation.tracking.geometry import enforce_side, side_of
from server.estimation.tracking.motion import step_noise_cov
from server.estimation.types import Fix, Step, step_displacement

_MIN_DIST = 1e-3


def _h_identity(x):
    return x


def _H_identity(x):
    return np.eye(2)


def range_h(x, beacon):
    return np.array([np.hypot(x[0] - beacon[0], x[1] - beacon[1])])


def range_H(x, beacon):
    dx, dy = x[0] - beacon[0], x[1] - beacon[1]
    r = max(np.hypot(dx, dy), _MIN_DIST)
    return np.array([[dx / r, dy / r]])


def parse_on_wall(on_wall, prior_mean) -> tuple[np.ndarray, float] | None:
    """``on_wall`` is None, a segment [x1, y1, x2, y2], or {"wall": [...], "side": ±1}.

    Without an explicit side, the allowed side is the one the prior mean is on
    (a beacon heard within 3 m is on the walker's side of its wall).
    """
    if on_wall is None:
        return None
    if isinstance(on_wall, dict):
        wall = np.asarray(on_wall["wall"], float)
        side = on_wall.get("side")
    else:
        wall, side = np.asarray(on_wall, float), None
    if wall.shape != (4,):
        raise ValueError("on_wall must be [x1, y1, x2, y2] or {'wall': [...], 'side': ±1}")
    if side is None:
        side = side_of(prior_mean, wall)
    return wall, float(np.sign(side))


@register
class EKFTracker(Tracker):
    name = "ekf"
    supports_range = True

    def __init__(
        self,
        initial_mean,
        initial_cov,
        walls=None,
        seed=None,
        q: float = 0.01,
        max_range_m: float = 3.0,
        wall_margin_m: float = 0.05,
    ):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.ekf = ExtendedKalmanFilter(dim_x=2, dim_z=2, dim_u=2)
        self.ekf.x = as_mean(initial_mean)
        self.ekf.P = as_cov(initial_cov)
        self.ekf.F = np.eye(2)
        self.ekf.B = np.eye(2)
        self.params = {"q": float(q), "max_range_m": float(max_range_m), "wall_margin_m": float(wall_margin_m)}

    def predict(self, step: Step) -> None:
        self.ekf.Q = step_noise_cov(step) + self.params["q"] * np.eye(2)
        self.ekf.predict(u=step_displacement(step.length_m, step.heading_deg))
        self._symmetrise()

    def update(self, fix: Fix) -> None:
        R = fix_cov(fix.covariance)
        self.ekf.update(np.asarray(fix.mean, float), _H_identity, _h_identity, R=R)
        self._symmetrise()

    def update_range(self, beacon_xy, range_m: float, range_std_m: float, on_wall=None) -> bool:
        if not np.isfinite(range_m) or range_m > self.params["max_range_m"] or range_std_m <= 0:
            return False
        beacon = np.asarray(beacon_xy, float).reshape(2)
        prior = self.mean
        constraint = parse_on_wall(on_wall, prior)
        if np.hypot(*(prior - beacon)) < _MIN_DIST:
            # Jacobian undefined exactly on the beacon: nudge along the first axis.
            self.ekf.x = prior + np.array([_MIN_DIST, 0.0])
        self.ekf.update(
            np.array([float(range_m)]),
            range_H,
            range_h,
            R=np.array([[float(range_std_m) ** 2]]),
            args=(beacon,),
            hx_args=(beacon,),
        )
        self._symmetrise()
        if constraint is not None:
            wall, side = constraint
            self.ekf.x, _ = enforce_side(self.ekf.x, wall, side, self.params["wall_margin_m"])
        return True

    def _symmetrise(self) -> None:
        self.ekf.P = 0.5 * (self.ekf.P + self.ekf.P.T)

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.ekf.x, float).reshape(2).copy()

    @property
    def covariance(self) -> np.ndarray:
        return np.asarray(self.ekf.P, float).copy()

    def reset(self, mean, cov) -> None:
        self.ekf.x = as_mean(mean)
        self.ekf.P = as_cov(cov)

    def _state(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist()}

    def _load_state(self, state: dict) -> None:
        self.ekf.x = np.asarray(state["mean"], float).reshape(2)
        self.ekf.P = np.asarray(state["cov"], float).reshape(2, 2)
