"""Systematic resampling with an explicit random offset.

Same algorithm as ``filterpy.monte_carlo.systematic_resample`` (N positions
(u + i)/N, i = 0..N−1, mapped through the cumulative weights), but the offset u comes
from the caller: filterpy draws it from numpy's *global* RNG, which a tracker cannot
serialise per session nor share safely between server threads. The tests pin this
function to filterpy's output for the same offset.
"""

from __future__ import annotations

import math

import numpy as np


def systematic_resample(weights: np.ndarray, u: float, n: int | None = None) -> np.ndarray:
    """Indexes of ``n`` (default: as many as weights) resampled particles for offset u in [0, 1)."""
    w = np.asarray(weights, float)
    n = w.shape[0] if n is None else int(n)
    positions = (u + np.arange(n)) / n
    cumulative = np.cumsum(w)
    cumulative[-1] = max(cumulative[-1], 1.0)  # guard against round-off below 1
    return np.searchsorted(cumulative, positions, side="right").astype(np.intp)


def effective_sample_size(weights: np.ndarray) -> float:
    return float(1.0 / np.sum(np.square(weights)))


def kld_count(xy: np.ndarray, bin_m: float, epsilon: float, n_min: int, n_max: int, z: float = 2.326) -> int:
    """How many particles a cloud needs (KLD-sampling, Fox 2003): enough that, with
    probability Φ(z) (0.99), the K–L divergence between the particle approximation and
    the true posterior stays below ``epsilon``, given the k bins (``bin_m`` squares) the
    positions ``xy`` occupy — a tight cloud needs few particles, a spread one many.
    Bounded to [n_min, n_max]."""
    k = len(np.unique(np.floor(np.asarray(xy, float) / bin_m).astype(np.int64), axis=0))
    if k <= 1:
        return int(n_min)
    a = 2.0 / (9.0 * (k - 1))
    n = (k - 1) / (2.0 * epsilon) * (1.0 - a + math.sqrt(a) * z) ** 3
    return int(min(max(math.ceil(n), n_min), n_max))
