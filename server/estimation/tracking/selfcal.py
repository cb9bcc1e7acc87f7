"""Self-calibrating PDR: the step model of the augmented (four-state) trackers.

State ``[x, y, b, s]``: position (site metres), the PDR's heading bias ``b`` (radians,
added to the phone's heading) and its step-length scale ``s`` (multiplies the phone's
length). A step of reported length d along reported heading h moves the walker by

    f(x, d, h) = (x + s·d·sin(h + b), y + s·d·cos(h + b), b, s)

and ``b`` and ``s`` drift as slow random walks (``bias_walk_deg`` and ``scale_walk`` of
standard deviation per step). Fixes measure ``[x, y]`` only; because a bias bends the
track away from the fixes in a way that correlates with the heading, the filters learn
``b`` and ``s`` from the fixes, and the dead reckoning between fixes is corrected.

Why: real PDR heading error is mostly a bias that accumulates (a magnetometer offset, a
phone held askew, gyro drift), so an independent-noise model lets the error grow like n
while the covariance grows like √n, and the innovation gate then refuses the very fixes
that would correct it.

The default noise levels come from data (``benchmarks/pdr_noise.py`` on the shared MSFT
walks, then a choice on the tune scenarios of ``benchmarks/scenario_family.py``; the
README's "Tracking design" gives the figures); the phone's own ``length_std_m`` and
``heading_std_deg`` are the white per-step part.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from server.estimation.types import Step

#: prior standard deviation of the heading bias at a session's start (degrees)
BIAS0_STD_DEG = 10.0
#: random-walk standard deviation of the heading bias per step (degrees)
BIAS_WALK_DEG = 1.0
#: prior standard deviation of the step-length scale (1 = the phone's lengths are right)
SCALE0_STD = 0.1
#: random-walk standard deviation of the step-length scale per step
SCALE_WALK = 0.003
#: the scale is kept in this range (a filter may not learn a walker who does not move)
SCALE_RANGE = (0.5, 2.0)

N_AUG = 4


def calibration_params(
    bias0_std_deg: float = BIAS0_STD_DEG,
    bias_walk_deg: float = BIAS_WALK_DEG,
    scale0_std: float = SCALE0_STD,
    scale_walk: float = SCALE_WALK,
) -> dict[str, float]:
    for k, v in (("bias0_std_deg", bias0_std_deg), ("bias_walk_deg", bias_walk_deg), ("scale0_std", scale0_std),
                 ("scale_walk", scale_walk)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{k} must be a finite number ≥ 0")
    return {"bias0_std_deg": float(bias0_std_deg), "bias_walk_deg": float(bias_walk_deg),
            "scale0_std": float(scale0_std), "scale_walk": float(scale_walk)}


def initial_state(mean2: np.ndarray, cov2: np.ndarray, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """[x, y, 0, 1] and blockdiag(P, σb0², σs0²) (floors keep P positive definite)."""
    x = np.array([mean2[0], mean2[1], 0.0, 1.0])
    P = np.zeros((N_AUG, N_AUG))
    P[:2, :2] = cov2
    P[2, 2] = max(math.radians(params["bias0_std_deg"]) ** 2, 1e-12)
    P[3, 3] = max(params["scale0_std"] ** 2, 1e-12)
    return x, P


def reset_position(x: np.ndarray, P: np.ndarray, mean2: np.ndarray, cov2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A restart of the position (snap, floor change) keeps what was learned of b and s."""
    x = x.copy()
    P = P.copy()
    x[:2] = mean2
    P[:2, :] = 0.0
    P[:, :2] = 0.0
    P[:2, :2] = cov2
    return x, P


def move(x: np.ndarray, d: float, h_rad: float) -> np.ndarray:
    """f(x, d, h) for one state (a copy)."""
    a = h_rad + x[2]
    sd = x[3] * d
    return np.array([x[0] + sd * math.sin(a), x[1] + sd * math.cos(a), x[2], x[3]])


def move_many(X: np.ndarray, d, h_rad) -> np.ndarray:
    """f for rows of states (n, 4); ``d`` and ``h_rad`` scalars or (n,) arrays."""
    a = h_rad + X[:, 2]
    sd = X[:, 3] * d
    out = X.copy()
    out[:, 0] += sd * np.sin(a)
    out[:, 1] += sd * np.cos(a)
    return out


def jacobians(x: np.ndarray, d: float, h_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """F = ∂f/∂x (4×4) and G = ∂f/∂(d, h) (4×2) at ``x``."""
    a = h_rad + x[2]
    sa, ca = math.sin(a), math.cos(a)
    s = x[3]
    F = np.eye(N_AUG)
    F[0, 2], F[0, 3] = s * d * ca, d * sa
    F[1, 2], F[1, 3] = -s * d * sa, d * ca
    G = np.array([[s * sa, s * d * ca], [s * ca, -s * d * sa], [0.0, 0.0], [0.0, 0.0]])
    return F, G


def step_input_var(step: Step) -> tuple[float, float]:
    """(σd², σh²) of the step's white noise, σh in radians."""
    return step.length_std_m**2, math.radians(step.heading_std_deg) ** 2


def process_noise(q: float, params: dict) -> np.ndarray:
    """diag(q, q, σb², σs²): position jitter and the random walks of b and s per step."""
    return np.diag([q, q, math.radians(params["bias_walk_deg"]) ** 2, params["scale_walk"] ** 2])


def clamp_calibration(b: float, s: float) -> tuple[float, float]:
    """Bias wrapped to (−π, π], scale kept in ``SCALE_RANGE``."""
    return math.remainder(b, 2 * math.pi), min(max(s, SCALE_RANGE[0]), SCALE_RANGE[1])


def clamp(x: np.ndarray) -> np.ndarray:
    """``clamp_calibration`` on a state [x, y, b, s] (a new array)."""
    x = np.asarray(x, float).copy()
    x[2], x[3] = clamp_calibration(float(x[2]), float(x[3]))
    return x


def symmetric(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.T)


class Calibrating:
    """Mixin of the augmented trackers: what they have learned, for reports and tests."""

    augmented = True

    @property
    def state_mean(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def state_covariance(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def heading_bias_deg(self) -> float:
        return math.degrees(float(self.state_mean[2]))

    @property
    def step_scale(self) -> float:
        return float(self.state_mean[3])


class FilterpyState:
    """Accessors and the stored form of a self-calibrating filter whose [x, y, b, s] and P live in
    a filterpy filter (``_kf``: the EKF's or the UKF's): both store ``mean``/``cov`` (the position)
    and ``x``/``P`` (the whole state), and load ``x``/``P``."""

    @property
    def _kf(self) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def state_mean(self) -> np.ndarray:
        return np.asarray(self._kf.x, float).reshape(N_AUG).copy()

    @property
    def state_covariance(self) -> np.ndarray:
        return np.asarray(self._kf.P, float).copy()

    @property
    def mean(self) -> np.ndarray:
        return self.state_mean[:2]

    @property
    def covariance(self) -> np.ndarray:
        return self.state_covariance[:2, :2]

    def _state(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist(),
                "x": self.state_mean.tolist(), "P": self.state_covariance.tolist()}

    def _load_state(self, state: dict) -> None:
        self._kf.x = np.asarray(state["x"], float).reshape(N_AUG)
        self._kf.P = np.asarray(state["P"], float).reshape(N_AUG, N_AUG)
