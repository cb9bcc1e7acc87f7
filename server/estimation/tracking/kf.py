"""KF: linear Kalman filter, heading taken as known, constant Q and R.

x⁻ = x + (d·sin h, d·cos h),  P⁻ = P + Q,  Q = q·I per step;
update with the fix mean z, H = I and a constant R = r·I (the fix's own covariance
is ignored — that is what distinguishes this baseline from the EKF).
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter

from server.estimation.tracking.base import Tracker, as_cov, as_mean, register, symmetric
from server.estimation.types import Fix, Step, step_displacement


class _LinearKF(Tracker):
    """Shared machinery for the linear position KFs (kf, fkf): a filterpy KalmanFilter
    with F = H = B = I."""

    def __init__(self, initial_mean, initial_cov, walls=None, seed=None, *, q: float, r: float):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.kf = KalmanFilter(dim_x=2, dim_z=2, dim_u=2)
        self.kf.x = as_mean(initial_mean)
        self.kf.P = as_cov(initial_cov)
        self.kf.F = np.eye(2)
        self.kf.B = np.eye(2)
        self.kf.H = np.eye(2)
        self.kf.Q = np.eye(2) * float(q)
        self.kf.R = np.eye(2) * float(r)
        self.params = {"q": float(q), "r": float(r)}

    def predict(self, step: Step) -> None:
        self.kf.predict(u=step_displacement(step.length_m, step.heading_deg))
        self.kf.P = symmetric(self.kf.P)

    def _kf_update(self, z: np.ndarray, R: np.ndarray) -> None:
        self.kf.update(np.asarray(z, float), R=R)
        self.kf.P = symmetric(self.kf.P)

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.kf.x, float).reshape(2).copy()

    @property
    def covariance(self) -> np.ndarray:
        return np.asarray(self.kf.P, float).copy()

    def reset(self, mean, cov) -> None:
        self.kf.x = as_mean(mean)
        self.kf.P = as_cov(cov)

    def _state(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist()}

    def _load_state(self, state: dict) -> None:
        self.kf.x = np.asarray(state["mean"], float).reshape(2)
        self.kf.P = np.asarray(state["cov"], float).reshape(2, 2)


@register
class KFTracker(_LinearKF):
    name = "kf"

    def __init__(self, initial_mean, initial_cov, walls=None, seed=None, q: float = 0.1, r: float = 4.0):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed, q=q, r=r)

    def update(self, fix: Fix) -> None:
        self._kf_update(fix.mean, self.kf.R)
