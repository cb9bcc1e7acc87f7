"""The vocabulary shared by fingerprint models and trackers.

Site frame: metres, x east, y north. ``heading_deg`` is clockwise from +y, so a step
of length d along heading h moves by (d·sin h, d·cos h). RSS is dBm in [-130, 0];
a transmitter not heard is absent from a scan (in arrays: NaN).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def step_displacement(length_m: float, heading_deg: float) -> np.ndarray:
    """The (dx, dy) of one step in the site frame."""
    h = math.radians(heading_deg)
    return np.array([length_m * math.sin(h), length_m * math.cos(h)])


@dataclass(frozen=True)
class Step:
    """One PDR step as the phone reports it."""

    t: float
    length_m: float
    heading_deg: float
    length_std_m: float = 0.1
    heading_std_deg: float = 5.0


@dataclass(frozen=True)
class Scan:
    """One RSS scan: transmitter id → dBm."""

    t: float
    rss: dict[str, float]
    heading_deg: float | None = None


@dataclass(frozen=True)
class Candidate:
    """A reference point with its posterior probability."""

    label: str
    x: float
    y: float
    floor: int
    probability: float


@dataclass(frozen=True)
class Fix:
    """A position estimate from one scan: mean, 2×2 covariance (m²) and floor."""

    x: float
    y: float
    floor: int
    covariance: np.ndarray
    reference_point: str | None = None
    candidates: list[Candidate] = field(default_factory=list)

    @property
    def mean(self) -> np.ndarray:
        return np.array([self.x, self.y])
