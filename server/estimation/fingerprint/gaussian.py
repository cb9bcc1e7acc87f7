"""Per-reference-point Gaussian statistics of the features (used by NBC and TKBE).

For reference point i and feature j: mean μ_ij and a variance shrunk towards a
pooled value, ``σ²_ij = (Σ (x − μ_ij)² + n0·s0²) / (n_i + n0)``, so reference points
with one or two scans do not get a zero variance. The Gaussian log-likelihood of a
query under every RP is three matrix products.
"""

from __future__ import annotations

import numpy as np


class GaussianRpStats:
    def __init__(self, X: np.ndarray, row_rp: np.ndarray, n_rp: int, prior_strength: float = 2.0,
                 min_var: float | None = None, pooled_var: float | None = None):
        X = np.asarray(X, dtype=np.float64)
        counts = np.bincount(row_rp, minlength=n_rp).astype(float)
        S = np.zeros((n_rp, X.shape[1]))
        np.add.at(S, row_rp, X)
        mu = S / np.maximum(counts, 1.0)[:, None]
        SS = np.zeros_like(S)
        np.add.at(SS, row_rp, X**2)
        dev2 = np.maximum(SS - counts[:, None] * mu**2, 0.0)  # Σ (x − μ)²
        if pooled_var is None:
            within = dev2 / np.maximum(counts - 1.0, 1.0)[:, None]
            heard = (mu > 0) & (counts[:, None] > 1)
            pooled_var = float(np.median(within[heard])) if heard.any() else 0.01
            if min_var is None:
                min_var = 0.25 * pooled_var
        pooled_var = max(pooled_var, 1e-8)
        var = (dev2 + prior_strength * pooled_var) / (counts[:, None] + prior_strength)
        if min_var is not None:
            var = np.maximum(var, min_var)
        self.mu = mu
        self.var = var
        self.counts = counts
        self.pooled_var = pooled_var
        inv = 1.0 / var
        self._inv = inv.T.copy()  # (m, n_rp)
        self._mu_inv = (mu * inv).T.copy()
        self._const = (mu**2 * inv).sum(axis=1) + np.log(var).sum(axis=1)

    def log_likelihood(self, Q: np.ndarray) -> np.ndarray:
        """(nq, m) → (nq, n_rp): Σ_j log N(q_j; μ_ij, σ²_ij) up to a constant."""
        Q = np.asarray(Q, dtype=np.float64)
        return -0.5 * ((Q**2) @ self._inv - 2.0 * Q @ self._mu_inv + self._const[None, :])
