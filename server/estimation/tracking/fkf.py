"""FKF: fuzzy-logic (adaptive-R) Kalman filter.

A linear KF (F = H = I) with Q = 0.225 m²·I per step and R switched by the size of
the residual ‖z − x⁻‖ of the fix being applied: < 1 m → 0.675, < 2 m → 1.125,
otherwise 1.575 m² on the diagonal (the fix's own covariance is not used).
Candidate reference points are restricted to a box of ±9 m around the last estimate:
``search_region()`` returns it for the fingerprint model.
PDR reset every 10 steps: the open-loop PDR track (``pdr_position``, steps only) is
re-anchored on the fused estimate every ``reset_every`` steps. The fused prediction
itself always starts from the last posterior (closed loop), so the reset bounds the
drift of the exposed PDR track rather than delaying fix feedback.
"""

from __future__ import annotations

import numpy as np

from server.estimation.tracking.base import as_mean, register
from server.estimation.tracking.kf import _LinearKF
from server.estimation.types import Fix, Step, step_displacement


@register
class FuzzyKFTracker(_LinearKF):
    name = "fkf"

    def __init__(
        self,
        initial_mean,
        initial_cov,
        walls=None,
        seed=None,
        q: float = 0.225,
        residual_thresholds_m: tuple[float, float] | list[float] = (1.0, 2.0),
        r_levels: tuple[float, float, float] | list[float] = (0.675, 1.125, 1.575),
        box_half_width_m: float = 9.0,
        reset_every: int = 10,
    ):
        r_levels = [float(v) for v in r_levels]
        thresholds = [float(v) for v in residual_thresholds_m]
        if len(r_levels) != len(thresholds) + 1 or thresholds != sorted(thresholds):
            raise ValueError("need len(r_levels) == len(residual_thresholds_m) + 1, thresholds ascending")
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed, q=q, r=r_levels[0])
        self.params = {
            "q": float(q),
            "residual_thresholds_m": thresholds,
            "r_levels": r_levels,
            "box_half_width_m": float(box_half_width_m),
            "reset_every": int(reset_every),
        }
        self.pdr = as_mean(initial_mean)
        self.steps_since_reset = 0
        self.last_residual_m: float | None = None
        self.last_r: float = r_levels[0]

    def r_for_residual(self, residual_m: float) -> float:
        for threshold, level in zip(self.params["residual_thresholds_m"], self.params["r_levels"]):
            if residual_m < threshold:
                return level
        return self.params["r_levels"][-1]

    def predict(self, step: Step) -> None:
        super().predict(step)
        self.pdr = self.pdr + step_displacement(step.length_m, step.heading_deg)
        self.steps_since_reset += 1
        if self.params["reset_every"] > 0 and self.steps_since_reset >= self.params["reset_every"]:
            self.pdr = self.mean
            self.steps_since_reset = 0

    def update(self, fix: Fix) -> None:
        z = np.asarray(fix.mean, float)
        residual = float(np.hypot(*(z - self.mean)))
        r = self.r_for_residual(residual)
        self._kf_update(z, np.eye(2) * r)
        self.last_residual_m, self.last_r = residual, r

    def search_region(self) -> tuple[float, float, float, float]:
        x, y = self.mean
        b = self.params["box_half_width_m"]
        return (float(x - b), float(y - b), float(x + b), float(y + b))

    @property
    def pdr_position(self) -> np.ndarray:
        return self.pdr.copy()

    def reset(self, mean, cov) -> None:
        super().reset(mean, cov)
        self.pdr = as_mean(mean)
        self.steps_since_reset = 0

    def _state(self) -> dict:
        return {
            **super()._state(),
            "pdr": self.pdr.tolist(),
            "steps_since_reset": self.steps_since_reset,
            "last_residual_m": self.last_residual_m,
            "last_r": self.last_r,
        }

    def _load_state(self, state: dict) -> None:
        super()._load_state(state)
        self.pdr = np.asarray(state["pdr"], float).reshape(2)
        self.steps_since_reset = int(state["steps_since_reset"])
        self.last_residual_m = state["last_residual_m"]
        self.last_r = float(state["last_r"])
