"""Support vector machines (RBF): floor by classification, position by regression.

1. Floor first: an RBF SVC over (building, floor) groups (skipped for one group).
2. Position: per group, two RBF SVRs (x and y, targets standardised).
3. Posterior over the reference points of the chosen floor:
   ``∝ exp(−|rp − ŝ|² / 2σ²)`` around the SVR estimate ŝ, σ the cross-validated RMS
   error per axis, so the fix's mean/covariance come from the same mixture reduction
   as every other model.

C and gamma (given, or None = searched): 3-fold cross-validation over a small grid
(C ∈ {1, 10, 100}, gamma ∈ {0.5, 1, 2} × sklearn's "scale") on at most ``cv_rows``
rows, within ``time_budget_s`` (grid points not reached in time are skipped; the
best so far wins). The final fits use all rows.
"""

from __future__ import annotations

import time

import numpy as np

from .base import FingerprintModel, TrainingData

# scikit-learn is imported where the SVM fits, not here: the registry imports this module in
# every training job, and the default model (wknn) never needs it (45 MB, 1.6 s per job)

C_GRID = (1.0, 10.0, 100.0)
GAMMA_FACTORS = (0.5, 1.0, 2.0)


class SVMModel(FingerprintModel):
    name = "svm"

    def __init__(self, C: float | None = None, gamma: float | None = None, time_budget_s: float = 120.0,
                 cv_rows: int = 2000, seed: int = 0, **common):
        common.setdefault("floor_classifier", None)  # has its own floor logic
        super().__init__(**common)
        self.C = C
        self.gamma = gamma
        self.time_budget_s = float(time_budget_s)
        self.cv_rows = int(cv_rows)
        self.seed = int(seed)

    def _design(self, X, H) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        if H is not None:
            X = np.hstack([X, self.heading_weight_ * np.asarray(H, dtype=np.float64)])
        return X

    def _grid(self, X):
        scale = 1.0 / (X.shape[1] * max(float(X.var()), 1e-12))
        Cs = (self.C,) if self.C is not None else C_GRID
        gammas = (self.gamma,) if self.gamma is not None else tuple(f * scale for f in GAMMA_FACTORS)
        return [(c, g) for c in Cs for g in gammas]

    def _fit(self, X, H, data: TrainingData) -> None:
        from sklearn.svm import SVC, SVR

        t0 = time.perf_counter()
        deadline = t0 + self.time_budget_s
        rng = np.random.default_rng(self.seed)
        Z = self._design(X, H)
        groups = data.row_group
        self.search_log_: list[tuple[str, float, float, float]] = []  # (stage, C, gamma, score)
        # 1. floor classifier
        self.svc_ = None
        if len(np.unique(groups)) > 1:
            params = self._search_svc(Z, groups, rng, t0 + 0.4 * self.time_budget_s)
            self.svc_ = SVC(C=params[0], gamma=params[1]).fit(Z, groups)
            self.svc_params_ = params
        # 2. position regressors per group, params searched on the largest group
        xy = np.column_stack([data.fs.x, data.fs.y])
        big = np.bincount(groups).argmax()
        (c, g), rms = self._search_svr(Z[groups == big], xy[groups == big], rng, deadline)
        self.svr_params_ = (c, g)
        self.sigma_ = max(rms / np.sqrt(2.0), self.cov_floor_m_)
        self.svr_ = {}
        for grp in np.unique(groups):
            rows = groups == grp
            mu, sd = xy[rows].mean(0), xy[rows].std(0) + 1e-9
            if rows.sum() < 2:
                self.svr_[grp] = (None, None, mu, sd)
                continue
            rx = SVR(C=c, gamma=g).fit(Z[rows], (xy[rows, 0] - mu[0]) / sd[0])
            ry = SVR(C=c, gamma=g).fit(Z[rows], (xy[rows, 1] - mu[1]) / sd[1])
            self.svr_[grp] = (rx, ry, mu, sd)
        self.search_time_s_ = time.perf_counter() - t0

    def _subsample(self, n, rng):
        if n <= self.cv_rows:
            return np.arange(n)
        return np.sort(rng.choice(n, self.cv_rows, replace=False))

    def _search_svc(self, Z, y, rng, deadline):
        from sklearn.model_selection import StratifiedKFold
        from sklearn.svm import SVC

        grid = self._grid(Z)
        if len(grid) == 1:
            return grid[0]
        idx = self._subsample(len(Z), rng)
        Zs, ys = Z[idx], y[idx]
        counts = np.bincount(ys)
        best, best_acc = grid[len(grid) // 2], -1.0
        if counts[counts > 0].min() < 3:  # too few scans per floor to cross-validate
            return best
        folds = list(StratifiedKFold(3, shuffle=True, random_state=self.seed).split(Zs, ys))
        for c, g in grid:
            if time.perf_counter() > deadline:
                break
            acc = np.mean([np.mean(SVC(C=c, gamma=g).fit(Zs[a], ys[a]).predict(Zs[b]) == ys[b]) for a, b in folds])
            self.search_log_.append(("svc", c, g, float(acc)))
            if acc > best_acc:
                best, best_acc = (c, g), acc
        return best

    def _search_svr(self, Z, xy, rng, deadline):
        from sklearn.model_selection import KFold
        from sklearn.svm import SVR

        grid = self._grid(Z)
        idx = self._subsample(len(Z), rng)
        Zs, xys = Z[idx], xy[idx]
        mu, sd = xys.mean(0), xys.std(0) + 1e-9
        T = (xys - mu) / sd
        if len(Zs) < 6:
            return grid[len(grid) // 2], 3.0
        folds = list(KFold(3, shuffle=True, random_state=self.seed).split(Zs))
        best, best_rms = grid[len(grid) // 2], np.inf
        for c, g in grid:
            if time.perf_counter() > deadline and np.isfinite(best_rms):
                break
            se = []
            for a, b in folds:
                px = SVR(C=c, gamma=g).fit(Zs[a], T[a, 0]).predict(Zs[b]) * sd[0] + mu[0]
                py = SVR(C=c, gamma=g).fit(Zs[a], T[a, 1]).predict(Zs[b]) * sd[1] + mu[1]
                se.append((px - xys[b, 0]) ** 2 + (py - xys[b, 1]) ** 2)
            rms = float(np.sqrt(np.mean(np.concatenate(se))))
            self.search_log_.append(("svr", c, g, rms))
            if rms < best_rms:
                best, best_rms = (c, g), rms
        return best, best_rms

    def _log_scores(self, Q, Hq, mask):
        Z = self._design(Q, Hq if self.use_heading else None)
        n = len(Z)
        g = self.svc_.predict(Z) if self.svc_ is not None else np.full(n, next(iter(self.svr_)))
        est = np.zeros((n, 2))
        for grp in np.unique(g):
            rows = g == grp
            rx, ry, mu, sd = self.svr_[grp]
            if rx is None:
                est[rows] = mu
            else:
                est[rows, 0] = rx.predict(Z[rows]) * sd[0] + mu[0]
                est[rows, 1] = ry.predict(Z[rows]) * sd[1] + mu[1]
        d2 = ((self.rp_xy_[None, :, :] - est[:, None, :]) ** 2).sum(-1)
        logs = -d2 / (2.0 * self.sigma_**2)
        return np.where(self.rp_group_[None, :] == g[:, None], logs, -np.inf)
