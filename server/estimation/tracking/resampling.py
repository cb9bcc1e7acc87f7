"""Systematic resampling with an explicit random offset.

Same algorithm as ``filterpy.monte_carlo.systematic_resample`` (N positions
(u + i)/N, i = 0..N−1, mapped through the cumulative weights), but the offset u comes
from the caller: filterpy draws it from numpy's *global* RNG, which a tracker cannot
serialise per session nor share safely between server threads. The tests pin this
function to filterpy's output for the same offset.
"""

from __future__ import annotations

import numpy as np


def systematic_resample(weights: np.ndarray, u: float) -> np.ndarray:
    """Indexes of the resampled particles for offset u in [0, 1)."""
    w = np.asarray(weights, float)
    n = w.shape[0]
    positions = (u + np.arange(n)) / n
    cumulative = np.cumsum(w)
    cumulative[-1] = max(cumulative[-1], 1.0)  # guard against round-off below 1
    return np.searchsorted(cumulative, positions, side="right").astype(np.intp)


def effective_sample_size(weights: np.ndarray) -> float:
    return float(1.0 / np.sum(np.square(weights)))
