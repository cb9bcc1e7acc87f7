"""KNN-preselected Bayesian estimation ("tkbe").

1. Preselect the K (default 15) reference points whose mean fingerprint is nearest to
   the query in RSS space.
2. Among them, multiply per-transmitter Gaussian likelihoods (the naive-Bayes
   statistics of nbc.py) into a posterior.
3. The MMSE position is that posterior's mean (the reduction in posterior.py); the
   floor is the one holding most of the posterior mass.
"""

from __future__ import annotations

import numpy as np

from .base import TrainingData
from .distance import SquaredDistance, smallest_columns
from .nbc import NBCModel


class TKBEModel(NBCModel):
    name = "tkbe"

    def __init__(self, n_preselect: int = 15, temperature: float = 1.0, prior_strength: float = 2.0, **common):
        super().__init__(temperature=temperature, prior_strength=prior_strength, **common)
        self.n_preselect = int(n_preselect)
        if self.n_preselect < 1:
            raise ValueError("n_preselect must be at least 1")

    def _fit(self, X, H, data: TrainingData) -> None:
        super()._fit(X, H, data)
        Hm = None
        if self.heading_stats_ is not None:  # set by NBCModel._fit exactly when H is given
            Hm = self.heading_stats_.mu
        self.rp_dist_ = SquaredDistance(self.stats_.mu, Hm, self.heading_weight_)

    def _log_scores(self, Q, Hq, mask):
        d2 = self.rp_dist_(Q, Hq)
        if mask is not None:
            d2 = np.where(mask, d2, np.inf)
        idx = smallest_columns(d2, self.n_preselect)
        keep = np.zeros(d2.shape, dtype=bool)
        np.put_along_axis(keep, idx, True, axis=1)
        keep &= np.isfinite(d2)
        ll = self._log_likelihood(Q, Hq) / self.temperature
        return np.where(keep, ll, -np.inf)
