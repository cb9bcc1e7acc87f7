"""FKF: fuzzy-logic (adaptive-R) Kalman filter.

A linear KF (F = H = I) with Q = 0.225 m²·I per step and R switched by the size of
the residual ‖z − x⁻‖ of the fix being applied. DESIGN.md gives the rule in absolute
units: < 1 m → 0.675, < 2 m → 1.125, otherwise 1.575 m² on the diagonal. Candidate
reference points are restricted to within 9 m of the last estimate (DESIGN's ±9 m box, as a circle):
``search_region()`` returns it for the fingerprint model.

Scaling to the fix (``scale="fix"``, the default). The literal numbers assume fixes
good to about a metre. On a real site a fingerprint fix is often 4–6 m off (variance
≈ 20 m²), so R ≤ 1.575 m² makes the filter trust every fix far more than it deserves
and — together with the box, which only lets the model answer near the current
estimate — lets a wrong estimate be confirmed by fixes pulled to the edge of the box:
the track random-walks away and stays lost (corridor benchmark: 43 m worst error).
So the rule is read in units of the fix's own spread σ = sqrt(trace(R_fix)/2), where
R_fix is the fingerprint model's covariance (floored like every tracker's R): the
thresholds are 1σ and 2σ and R = level·σ²·I with the levels 0.675, 1.125, 1.575 kept
as relative levels (multiples of σ²). With σ = 1 m this is exactly DESIGN's rule;
``scale="none"`` restores the literal metres/m² (``residual_thresholds_m`` and
``r_levels`` then mean m and m²).

Lost track. A residual at or above the last threshold is "large". After
``lost_after`` (3) large residuals in a row the track is taken as lost and the box is
released (``search_region()`` returns None) so the model may answer anywhere and the
fixes can pull the estimate back; the box returns, centred on the estimate, with the
first fix whose residual is not large. ``lost_after=0`` keeps the box always.

PDR reset every 10 steps: the open-loop PDR track (``pdr_position``, steps only) is
re-anchored on the fused estimate every ``reset_every`` steps. The fused prediction
itself always starts from the last posterior (closed loop), so the reset bounds the
drift of the exposed PDR track rather than delaying fix feedback.
"""

from __future__ import annotations

import math

import numpy as np

from server.estimation.tracking.base import as_mean, fix_cov_entries, register
from server.estimation.tracking.kf import _LinearKF
from server.estimation.types import Area, Fix, Step, step_displacement

SCALES = ("fix", "none")


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
        scale: str = "fix",
        lost_after: int = 3,
    ):
        if scale not in SCALES:
            raise ValueError(f"scale must be one of {SCALES}")
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
            "scale": scale,
            "lost_after": int(lost_after),
        }
        self.large_residuals = 0  # consecutive fixes with a residual at or above the last threshold
        self.pdr = as_mean(initial_mean)
        self.steps_since_reset = 0
        self.last_residual_m: float | None = None
        self.last_r: float = r_levels[0]

    def _level(self, residual: float) -> int:
        for i, threshold in enumerate(self.params["residual_thresholds_m"]):
            if residual < threshold:
                return i
        return len(self.params["residual_thresholds_m"])

    def fix_sigma(self, fix: Fix) -> float:
        """The fix's own spread σ = sqrt(trace(R_fix)/2) (m); 1 when ``scale="none"``."""
        if self.params["scale"] == "none":
            return 1.0
        r00, _, r11 = fix_cov_entries(fix.covariance)
        return math.sqrt(0.5 * (r00 + r11))

    @property
    def lost(self) -> bool:
        """Whether the last ``lost_after`` fixes all had large residuals (the box is released)."""
        n = self.params["lost_after"]
        return n > 0 and self.large_residuals >= n

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
        sigma = self.fix_sigma(fix)
        level = self._level(residual / sigma)
        r = self.params["r_levels"][level] * sigma * sigma
        self._kf_update(z, np.eye(2) * r)
        self.last_residual_m, self.last_r = residual, r
        top = len(self.params["residual_thresholds_m"])
        self.large_residuals = self.large_residuals + 1 if level == top else 0

    def search_region(self) -> Area | None:
        """Within ``box_half_width_m`` of the estimate (DESIGN's ±9 m box, as the circle the
        fingerprint model restricts to); None while lost, and before the filter is localised within
        it (its largest position σ above the half-width): the box around a wrong cold start would keep
        every later fix near it (MSFT folds 0–1: cold 11.2 m with it, 10.2 without)."""
        b = self.params["box_half_width_m"]
        if self.lost or np.sqrt(np.linalg.eigvalsh(self.covariance)[-1]) > b:
            return None
        x, y = self.mean
        return Area(float(x), float(y), b)

    @property
    def pdr_position(self) -> np.ndarray:
        return self.pdr.copy()

    def reset(self, mean, cov) -> None:
        super().reset(mean, cov)
        self.pdr = as_mean(mean)
        self.steps_since_reset = 0
        self.large_residuals = 0

    def _state(self) -> dict:
        return {
            **super()._state(),
            "pdr": self.pdr.tolist(),
            "steps_since_reset": self.steps_since_reset,
            "last_residual_m": self.last_residual_m,
            "last_r": self.last_r,
            "large_residuals": self.large_residuals,
        }

    def _load_state(self, state: dict) -> None:
        super()._load_state(state)
        self.pdr = np.asarray(state["pdr"], float).reshape(2)
        self.steps_since_reset = int(state["steps_since_reset"])
        self.last_residual_m = state["last_residual_m"]
        self.last_r = float(state["last_r"])
        self.large_residuals = int(state.get("large_residuals", 0))
