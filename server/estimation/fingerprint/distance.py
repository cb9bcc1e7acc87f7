"""Squared Euclidean distances from queries to many fingerprints, using sparsity.

Features are 0 for "not heard" and a scan hears a few dozen of hundreds of
transmitters, so the fingerprint matrix is kept in CSR form and
``|q − f|² = |q|² + |f|² − 2 q·f`` costs one sparse product per batch.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse


class SquaredDistance:
    def __init__(self, X: np.ndarray, H: np.ndarray | None = None, heading_weight: float = 0.0):
        X = np.asarray(X, dtype=np.float32)
        self.F = sparse.csr_matrix(X)
        self.f2 = np.asarray(X.astype(np.float64) ** 2).sum(axis=1)
        self.H = None if H is None else np.asarray(H, dtype=np.float64) * heading_weight
        self.h2 = None if self.H is None else (self.H**2).sum(axis=1)
        self.heading_weight = heading_weight

    def __call__(self, Q: np.ndarray, Hq: np.ndarray | None = None) -> np.ndarray:
        """(nq, m) features [+ (nq, 2) heading features] → (nq, n) squared distances."""
        Q = np.asarray(Q, dtype=np.float32)
        cross = np.asarray((self.F @ Q.T).T, dtype=np.float64)
        d2 = (Q.astype(np.float64) ** 2).sum(axis=1)[:, None] + self.f2[None, :] - 2.0 * cross
        if self.H is not None and self.h2 is not None and Hq is not None:  # h2 is None iff H is
            hq = np.asarray(Hq, dtype=np.float64) * self.heading_weight
            d2 += (hq**2).sum(axis=1)[:, None] + self.h2[None, :] - 2.0 * hq @ self.H.T
        np.maximum(d2, 0.0, out=d2)
        return d2
