"""Step length from the acceleration swing of each step.

* Weinberg: ``L = k·(a_max − a_min)^(1/4)``, k ≈ 0.35–0.5 depending on the person
  and where the phone is carried.
* Quadratic in the peak acceleration: ``L = c0 + c1·a_max + c2·a_max²``.

Both are calibrated from a walk of known length (:func:`calibrate_weinberg`,
:func:`calibrate_quadratic`), as a phone app does with "walk 20 m".
"""

from __future__ import annotations

import numpy as np

DEFAULT_WEINBERG_K = 0.45


def weinberg(a_max: np.ndarray, a_min: np.ndarray, k: float = DEFAULT_WEINBERG_K) -> np.ndarray:
    return k * np.maximum(np.asarray(a_max) - np.asarray(a_min), 0.0) ** 0.25


def calibrate_weinberg(a_max: np.ndarray, a_min: np.ndarray, distance_m: float) -> float:
    """The k that makes the Weinberg lengths of these steps add up to ``distance_m``."""
    total = weinberg(a_max, a_min, 1.0).sum()
    if total <= 0:
        raise ValueError("no acceleration swing to calibrate on")
    return float(distance_m / total)


def quadratic(a_max: np.ndarray, coeffs: tuple[float, float, float]) -> np.ndarray:
    c0, c1, c2 = coeffs
    a = np.asarray(a_max)
    return c0 + c1 * a + c2 * a * a


def calibrate_quadratic(a_max: np.ndarray, lengths_m: np.ndarray) -> tuple[float, float, float]:
    """Least-squares coefficients from steps of known length (needs a spread of speeds)."""
    a = np.asarray(a_max, dtype=float)
    c2, c1, c0 = np.polyfit(a, np.asarray(lengths_m, dtype=float), 2)
    return float(c0), float(c1), float(c2)
