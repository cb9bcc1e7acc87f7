"""Measurement models shared by the nonlinear trackers (EKF, UKF, PF).

- fix: z = x, H = I (R = the fix's covariance);
- beacon range, in log-range (``log_range``): h(x) = ln‖x − beacon‖, H = (x − b)ᵀ/‖x − b‖²,
  R = (σ_r / r)², used only within ``max_range_m`` of the beacon (``range_usable``);
- wall side: a beacon mounted on a wall is heard on one side of it (``WallSide``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from server.estimation.tracking.geometry import side_of

#: below this distance from the beacon the range Jacobian is undefined
MIN_RANGE_M = 1e-3


def fix_h(x: np.ndarray) -> np.ndarray:
    """A fix measures the position: the first two components of any state ``[x, y, ...]``."""
    return x[:2]


def fix_H(x: np.ndarray) -> np.ndarray:
    """Jacobian of ``fix_h``: ``[I₂ 0]`` (2×n)."""
    return np.eye(2, len(x))


#: distances below this are taken as this in log-range (a walker is never closer to a beacon)
MIN_LOG_RANGE_M = 0.1


def log_range(range_m: float, range_std_m: float) -> tuple[float, float]:
    """A beacon range as the measurement the trackers use: (ln r, σ of ln r).

    The log-distance path-loss model's error is Gaussian in dB, so the range's error is
    log-normal: its first-order std ``range_std_m`` (∝ r, ``radio.range_std_from_rss``) is
    ``r·σ_ln``. Weighing a particle (or linearising) in log-range keeps that shape; a
    Gaussian in range itself, with the narrow std of a short range, made a strong reading
    (a beacon 10 m away heard as 2.4 ± 1 m through shadowing) a 7σ event that left one
    particle of a thousand alive, where the dB model gives it 3σ."""
    return math.log(max(range_m, MIN_LOG_RANGE_M)), range_std_m / max(range_m, MIN_LOG_RANGE_M)


def log_range_h(x: np.ndarray, beacon: np.ndarray) -> np.ndarray:
    """ln of the distance from the position ``x[:2]`` to the beacon (floored at ``MIN_LOG_RANGE_M``), as a 1-vector."""
    return np.array([math.log(max(math.hypot(x[0] - beacon[0], x[1] - beacon[1]), MIN_LOG_RANGE_M))])


def log_range_H(x: np.ndarray, beacon: np.ndarray) -> np.ndarray:
    """Jacobian of ``log_range_h`` (1×n: (x − b)ᵀ/d², zero beyond the position)."""
    dx, dy = x[0] - beacon[0], x[1] - beacon[1]
    d2 = max(dx * dx + dy * dy, MIN_LOG_RANGE_M**2)
    H = np.zeros((1, len(x)))
    H[0, 0], H[0, 1] = dx / d2, dy / d2
    return H


def range_usable(range_m: float, range_std_m: float, max_range_m: float) -> bool:
    """Whether a beacon range is worth an update: finite, close enough, positive spread
    (far ranges are too noisy for the log-distance model)."""
    return bool(np.isfinite(range_m)) and range_m <= max_range_m and range_std_m > 0


@dataclass(frozen=True)
class WallSide:
    """The estimate must stay on ``side`` (+1 left / −1 right) of ``wall`` [x1, y1, x2, y2]."""

    wall: np.ndarray
    side: float


def parse_on_wall(on_wall: Any, prior_mean) -> WallSide | None:
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
    return WallSide(wall, float(np.sign(side)))
