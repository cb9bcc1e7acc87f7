"""How well an answer's covariance matches its error: the squared Mahalanobis distance of the
error under the claimed covariance (an estimate's NEES, a fix's NIS against the truth; 2 on
average in 2-D when the covariance is honest)."""

from __future__ import annotations

import numpy as np


def squared_mahalanobis(dx: float, dy: float, cov) -> float:
    """dᵀC⁻¹d for the error d = (dx, dy) under the 2×2 covariance ``cov`` (m²)."""
    d = np.array([dx, dy], dtype=float)
    return float(d @ np.linalg.solve(np.asarray(cov, dtype=float), d))
