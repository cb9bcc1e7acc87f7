"""Gaussian naive Bayes over reference points.

Each reference point is a class; every feature (transmitter, in the chosen
missing-value representation) is an independent Gaussian per class (see
gaussian.py). With ``use_heading`` the heading's (sin, cos) are two more Gaussian
features per class, used only when the query carries a heading. Uniform prior over
reference points; ``temperature`` > 1 flattens the (typically overconfident)
posterior.
"""

from __future__ import annotations

import numpy as np

from .base import FingerprintModel, TrainingData
from .gaussian import GaussianRpStats


class NBCModel(FingerprintModel):
    name = "nbc"

    def __init__(self, temperature: float = 1.0, prior_strength: float = 2.0, **common):
        super().__init__(**common)
        self.temperature = float(temperature)
        self.prior_strength = float(prior_strength)

    def _fit(self, X, H, data: TrainingData) -> None:
        n_rp = len(data.rp)
        self.stats_ = GaussianRpStats(X, data.rp.row_rp, n_rp, self.prior_strength)
        self.heading_stats_ = None
        if H is not None:
            known = ~np.isnan(data.fs.heading_deg)
            self.heading_stats_ = GaussianRpStats(
                H[known], data.rp.row_rp[known], n_rp, self.prior_strength, min_var=0.02, pooled_var=0.5
            )

    def _log_likelihood(self, Q, Hq) -> np.ndarray:
        ll = self.stats_.log_likelihood(Q)
        if self.heading_stats_ is not None and Hq is not None:
            has = np.any(Hq != 0, axis=1)
            if has.any():
                ll[has] += self.heading_stats_.log_likelihood(Hq[has])
        return ll

    def _log_scores(self, Q, Hq, mask):
        return self._log_likelihood(Q, Hq) / self.temperature
