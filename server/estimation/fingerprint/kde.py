"""Kernel density posterior: Gaussian kernels in RSS space.

``p(s | rp) = mean over the fingerprints f of rp of exp(−|s − f|² / 2h²)``, uniform
prior over reference points; the fix is the mixture mean and covariance (its R).
Bandwidth h: given, or (None) chosen on the training data: leave-one-out on up to
``n_tune`` fingerprints, over multiples of the RMS distance of scans to their own
reference point's mean fingerprint, minimising the mean position error. For tracking, pass ``near=previous_fix, radius_m=...`` to
`locate` to restrict the posterior to reference points near the previous estimate
("spatial filtering").
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from .base import FingerprintModel, TrainingData
from .distance import SquaredDistance


class KDEModel(FingerprintModel):
    name = "kde"

    def __init__(self, bandwidth: float | None = None, n_tune: int = 400, **common):
        super().__init__(**common)
        self.bandwidth = bandwidth
        self.n_tune = int(n_tune)

    def _fit(self, X, H, data: TrainingData) -> None:
        row_rp = data.rp.row_rp
        n_rp = len(data.rp)
        self.dist_ = SquaredDistance(X, H, self.heading_weight_)
        self.row_rp_ = row_rp
        counts = np.bincount(row_rp, minlength=n_rp).astype(float)
        self.log_counts_ = np.log(np.maximum(counts, 1.0))
        self.onehot_ = sparse.csr_matrix(
            (np.ones(len(row_rp)), (np.arange(len(row_rp)), row_rp)), shape=(len(row_rp), n_rp)
        )
        if self.bandwidth is not None:
            self.bandwidth_ = float(self.bandwidth)
        else:
            mean = np.zeros((n_rp, X.shape[1]))
            np.add.at(mean, row_rp, X)
            mean /= np.maximum(counts, 1)[:, None]
            d2 = ((X - mean[row_rp]) ** 2).sum(axis=1)
            d2 = d2[counts[row_rp] > 1]
            h0 = float(np.sqrt(np.mean(d2))) if len(d2) and np.mean(d2) > 0 else 0.1
            self.bandwidth_ = self._tune_bandwidth(X, H, data, h0)

    def _tune_bandwidth(self, X, H, data: TrainingData, h0: float) -> float:
        n = len(X)
        if n < 10:
            return h0
        rng = np.random.default_rng(0)
        pick = rng.choice(n, size=min(self.n_tune, n), replace=False)
        d2 = self.dist_(X[pick], None if H is None else H[pick])
        d2[np.arange(len(pick)), pick] = np.inf  # leave one out
        true_xy = np.column_stack([data.fs.x[pick], data.fs.y[pick]])
        best, best_err = h0, np.inf
        for f in (0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0):
            self.bandwidth_ = h0 * f
            logs = self._scores_from_d2(d2)
            pred = self._reduce(logs)
            err = float(np.mean(np.hypot(pred.x - true_xy[:, 0], pred.y - true_xy[:, 1])))
            if err < best_err:
                best, best_err = h0 * f, err
        return best

    def _log_scores(self, Q, Hq, mask):
        d2 = self.dist_(Q, Hq)
        if mask is not None:
            d2 = np.where(mask[:, self.row_rp_], d2, np.inf)
        return self._scores_from_d2(d2)

    def _scores_from_d2(self, d2):
        z = -d2 / (2.0 * self.bandwidth_**2)
        zmax = np.max(z, axis=1, keepdims=True)
        zmax = np.where(np.isfinite(zmax), zmax, 0.0)
        K = np.exp(z - zmax)
        S = np.asarray((self.onehot_.T @ K.T).T)
        with np.errstate(divide="ignore"):
            return np.log(S) + zmax - self.log_counts_[None, :]
