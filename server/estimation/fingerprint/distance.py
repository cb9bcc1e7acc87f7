"""Distances from queries to many fingerprints, and the k nearest of them.

Features are 0 for "not heard" and a scan hears a few dozen of hundreds of
transmitters, so the fingerprint matrix is kept in CSR form and
``|q − f|² = |q|² + |f|² − 2 q·f`` costs one sparse product per batch
(``SquaredDistance``). ``smallest_columns``, ``nearest_columns`` and ``weighted_vote`` pick
and vote from a (queries × fingerprints) distance matrix, for the models and the floor
classifier alike.
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


def smallest_columns(D: np.ndarray, k: int) -> np.ndarray:
    """(n, k') column indices of each row's k' = min(k, columns) smallest values (k' ≥ 1), in no order."""
    k = max(1, min(k, D.shape[1]))
    return np.argpartition(D, k - 1, axis=1)[:, :k] if k < D.shape[1] else np.tile(np.arange(D.shape[1]), (len(D), 1))


def nearest_columns(D: np.ndarray, k: int) -> np.ndarray:
    """``smallest_columns`` with each row's indices nearest first."""
    idx = smallest_columns(D, k)
    return np.take_along_axis(idx, np.argsort(np.take_along_axis(D, idx, axis=1), axis=1), axis=1)


def weighted_vote(D: np.ndarray, labels: np.ndarray, k: int, n_labels: int) -> np.ndarray:
    """Per row, the label (0 … n_labels − 1, ``labels`` per column) with the largest sum of 1/d
    weights among the row's k nearest columns (an infinite distance weighs nothing; ties: the
    smallest label)."""
    idx = smallest_columns(D, k)
    d = np.take_along_axis(D, idx, axis=1)
    w = np.where(np.isfinite(d), 1.0 / (d + 1e-6), 0.0)
    return np.argmax(row_sums(labels[idx], w, n_labels), axis=1)


def row_sums(labels: np.ndarray, w: np.ndarray, n_labels: int) -> np.ndarray:
    """(n, k) labels in 0 … n_labels − 1 and their weights → (n, n_labels): each row's weights
    summed per label (``np.add.at`` as one ``bincount``, in the same order: several times cheaper)."""
    n = len(labels)
    flat = (np.arange(n)[:, None] * n_labels + labels).ravel()
    return np.bincount(flat, weights=np.ravel(w), minlength=n * n_labels).reshape(n, n_labels)
