"""Interpolated radio map ("rmap"): fixes between survey points, for sparse surveys.

A fingerprint model over the surveyed points can only answer a surveyed point (or a
weighted mean of a few): on a floor walked along a handful of lines, a scan taken
between them is pulled onto the nearest line. This model adds virtual reference points
between them, from a radio map interpolated over the floor:

1. **Map.** Per (building, floor), each transmitter's encoded RSS (features.py; "not
   heard" is 0, so the map holds how strongly *and how often* a transmitter is heard)
   is a Nadaraya–Watson kernel regression over the floor of the survey's reference
   points (Gaussian kernel of length scale ``length_scale_m``, each point weighted by
   its number of scans, cut at 3 length scales: a sparse matrix product), evaluated at
   the cells of a ``grid_m`` grid within ``reach_m`` of at least two surveyed points
   (no extrapolation into unsurveyed wings; near a single point a cell would only
   repeat it). The model's reference points are the surveyed points (their own mean
   fingerprints, so a scan where someone surveyed still finds its point) and the cells.
2. **Query.** The ``k`` nearest of them on the chosen floor in feature space (Sørensen
   distance, as wknn's) vote with weights 1/d^``weight_power``: the posterior, reduced
   to a fix and covariance as for every model (posterior.py). The floor comes from the
   base class's floor classifier, extra trees by default (the only part that uses the
   heading: the map has none). On 1,500 scans of UJIIndoorLoc's choosing users (ℓ = 6 m,
   k = 5): mean 10.7 m with the trees, 11.0 m with the model's own posterior mass, 17.1 m
   with the SVC.
3. **Choices.** ``length_scale_m`` and ``k`` (when None) are chosen by an internal
   cross-validation that holds out whole survey walks (devices, when each point was
   surveyed by one of at least 3), else whole reference points, and locates their scans
   against a map built without them — a scan taken where nobody surveyed. The fix
   covariance is calibrated on the same held-out fixes (calibration.py); the server's
   training step refits the calibration on its own held-out sample.

Meant for sparse surveys (walks, a few points per room): on a dense survey the cells
add little over wknn and cost memory and fit time. No per-query device offset (wknn
has one). The artifact stores the survey's reference points, not the map: the map is
rebuilt, identically, when the model is loaded.

Measured on the MSFT site-1 F1 walks (``client_sim msft --folds 4``; the encoding,
grids, reach and weight power chosen on folds 0–1 with benchmarks/radiomap_msft.py),
reported on folds 2–3 through the API: fingerprinting alone 11.30 m mean, p90 26.9 m,
against wknn 13.59 / 35.6 and knn 15.42 / 41.7 (medians alike, 7.9–8.2 m) — with the
ℓ = 12 m, k = 25 the training step's split chose; fitted in process on all map walks
the cross-validation chose ℓ = 4–6 m and gave 12.88 m against wknn's 13.07 (on ~30
walks the choice is noisy: benchmarks/radiomap_msft.py --folds 2,3). Trackers
fed its fixes were not better there (pf 3.61 m against 3.32 with knn's fixes, which the
training step's calibration trusts far less), though they were on folds 0–1 (pf 4.51
against 4.77). On UJIIndoorLoc (dense; the reporting users of
benchmarks/fingerprint_choice.py) 13.5 m against wknn's 12.0 m, with a 7× longer fit.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from .base import FingerprintModel, TrainingData
from .calibration import fit_calibration
from .dataset import ReferencePoints, rp_display_label
from .distance import nearest_columns
from .posterior import reduce_live

CV_FOLDS = 5
#: kernel weights beyond this many length scales are dropped (e^-4.5 ≈ 1 %)
KERNEL_CUT = 3.0


def _grid_cells(xy: np.ndarray, grid_m: float, reach_m: float) -> np.ndarray:
    """(c, 2) centres of the ``grid_m`` cells within ``reach_m`` of at least two points of
    ``xy`` (a cell near a single point would only repeat that point's fingerprint) and not
    within half a step of one (the point itself stands there)."""
    if len(xy) < 2:
        return np.zeros((0, 2))
    lo = np.floor((xy.min(axis=0) - reach_m) / grid_m) * grid_m
    hi = xy.max(axis=0) + reach_m
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1e-9, grid_m), np.arange(lo[1], hi[1] + 1e-9, grid_m))
    cells = np.column_stack([gx.ravel(), gy.ravel()])
    d, _ = cKDTree(xy).query(cells, k=2, distance_upper_bound=reach_m + 1e-9)
    return cells[np.isfinite(d[:, 1]) & (d[:, 0] >= 0.5 * grid_m)]


def _kernel_weights(cells: np.ndarray, xy: np.ndarray, weight: np.ndarray, length_scale_m: float) -> sparse.csr_matrix:
    """(c, p) sparse row-normalised kernel weights of the points ``xy`` (each also weighted by
    ``weight``) at ``cells``, cut at ``KERNEL_CUT`` length scales; a cell beyond the cut from
    every point takes its nearest point. The map at the cells is ``W @ F`` (F the points'
    encoded fingerprints: sparse too, a scan hears a few of the site's transmitters)."""
    points = cKDTree(xy)
    D = cKDTree(cells).sparse_distance_matrix(points, KERNEL_CUT * length_scale_m, output_type="coo_matrix")
    W = sparse.csr_matrix((np.exp(-0.5 * (D.data / length_scale_m) ** 2) * weight[D.col], (D.row, D.col)),
                          shape=(len(cells), len(xy)))
    lonely = np.flatnonzero(np.diff(W.indptr) == 0)
    if len(lonely):
        W = W + sparse.csr_matrix((np.ones(len(lonely)), (lonely, points.query(cells[lonely])[1])), shape=W.shape)
    return sparse.csr_matrix(sparse.diags(1.0 / np.asarray(W.sum(axis=1)).ravel()) @ W)


class RadioMapModel(FingerprintModel):
    """length_scale_m: the kernel's length scale (m; None = chosen by cross-validation
    among ``length_grid``); grid_m: cell spacing (m); reach_m: cells farther than this
    from every surveyed point are left out; k: cells voting for the position (None =
    chosen among ``k_grid``); weight_power: the k vote with weights 1/d^p (a sharp p
    lets an exact match, a scan where someone surveyed, outweigh the smoother cells
    around it); calibrate: fit ``calibration_`` on the cross-validation's
    held-out fixes; cv_rows: held-out scans the cross-validation locates at most."""

    name = "rmap"

    def __init__(self, length_scale_m: float | None = None, length_grid: tuple[float, ...] = (3.0, 4.0, 6.0, 8.0, 12.0),
                 grid_m: float = 2.0, reach_m: float = 6.0, k: int | None = None,
                 k_grid: tuple[int, ...] = (3, 5, 9, 15, 25), weight_power: float = 8.0, calibrate: bool = True,
                 cv_rows: int = 1500, missing: str = "powed", floor_classifier: str | None = "trees", **common):
        super().__init__(missing=missing, floor_classifier=floor_classifier, **common)
        self.length_scale_m = None if length_scale_m is None else float(length_scale_m)
        self.length_grid = tuple(float(v) for v in length_grid)
        self.grid_m = float(grid_m)
        self.reach_m = float(reach_m)
        self.k = None if k is None else int(k)
        self.k_grid = tuple(int(v) for v in k_grid)
        self.weight_power = float(weight_power)
        self.calibrate = bool(calibrate)
        self.cv_rows = int(cv_rows)
        scales = self.length_grid + (() if self.length_scale_m is None else (self.length_scale_m,))
        if not scales or min(scales) <= 0:
            raise ValueError("length scales must be positive (and length_grid not empty)")
        if self.grid_m <= 0 or self.reach_m < 0:
            raise ValueError("grid_m must be positive and reach_m not negative")
        ks = self.k_grid + (() if self.k is None else (self.k,))
        if not ks or min(ks) < 1:
            raise ValueError("k must be at least 1 (and k_grid not empty)")
        if self.weight_power <= 0:
            raise ValueError("weight_power must be positive")
        if self.cv_rows < CV_FOLDS:
            raise ValueError(f"cv_rows must be at least {CV_FOLDS}")

    # ---- state: the artifact keeps the survey, the grid is rebuilt ----------------------
    def __getstate__(self) -> dict:
        state = dict(vars(self))
        for name in ("GT_", "g_sum_", "rp_xy_", "rp_group_", "rp_", "rp_key_index_"):
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        vars(self).update(state)
        if hasattr(self, "survey_F_"):
            self._build_map()

    # ---- fit -----------------------------------------------------------------------------
    def _fit(self, X, H, data: TrainingData) -> None:
        rp = data.rp
        F, weight = self._rp_means(X, rp.row_rp, len(rp))
        self.survey_xy_ = rp.xy
        self.survey_rp_ = rp
        self.survey_group_ = self.rp_group_.copy()
        self.survey_weight_ = weight
        self.survey_F_ = F
        self.length_scale_m_ = self.length_scale_m if self.length_scale_m is not None else 4.0
        self.k_ = self.k if self.k is not None else 5
        if self.length_scale_m is None or self.k is None or self.calibrate:
            self._cross_validate(X, data)
        self._build_map()

    @staticmethod
    def _rp_means(X: np.ndarray, row_rp: np.ndarray, n_rp: int) -> tuple[sparse.csr_matrix, np.ndarray]:
        """Each reference point's mean encoded fingerprint (sparse (n_rp, m)) and scan count."""
        counts = np.bincount(row_rp, minlength=n_rp).astype(float)
        A = sparse.csr_matrix((1.0 / counts[row_rp], (row_rp, np.arange(len(row_rp)))), shape=(n_rp, len(row_rp)))
        return sparse.csr_matrix(A @ sparse.csr_matrix(np.asarray(X, dtype=np.float64))), counts

    def _map(self, xy, group, weight, F, length_scale_m, cols=None):
        """The cells of the points (xy, group, weight, F) as (cells (c, 2), their groups,
        their map (m, c) float32 — only the transmitter columns ``cols`` when given —, and
        each cell's feature sum over every transmitter, (c,) float64): the points
        themselves with their own fingerprints first, then the grid cells of each group
        with the kernel regression."""
        Fc = F if cols is None else F[:, cols]
        cells, cell_group = [xy], [group]
        maps, sums = [np.asarray(Fc.T.toarray(), dtype=np.float32)], [np.asarray(F.sum(axis=1)).ravel()]
        for g in np.unique(group):
            on = np.flatnonzero(group == g)
            c = _grid_cells(xy[on], self.grid_m, self.reach_m)
            if len(c):
                W = _kernel_weights(c, xy[on], weight[on], length_scale_m)
                cells.append(c)
                cell_group.append(np.full(len(c), g))
                maps.append(np.asarray((W @ Fc[on]).toarray(), dtype=np.float32).T)
                sums.append(W @ sums[0][on])
        return (np.concatenate(cells), np.concatenate(cell_group), np.ascontiguousarray(np.hstack(maps)),
                np.concatenate(sums))

    def _build_map(self) -> None:
        """The survey's reference points and the grid cells become the model's reference
        points; ``GT_`` is their map."""
        cells, cell_group, self.GT_, self.g_sum_ = self._map(self.survey_xy_, self.survey_group_, self.survey_weight_,
                                                             self.survey_F_, self.length_scale_m_)
        n = len(self.survey_xy_)
        grid = [(int(self.group_building_[g]), int(self.group_floor_[g]), "P", round(float(x), 3), round(float(y), 3))
                for g, (x, y) in zip(cell_group[n:], cells[n:], strict=True)]
        keys = list(self.survey_rp_.keys) + grid
        self.rp_xy_ = cells
        self.rp_group_ = cell_group
        self.rp_ = ReferencePoints(keys=keys, labels=list(self.survey_rp_.labels) + [rp_display_label(k) for k in grid],
                                   x=cells[:, 0].copy(), y=cells[:, 1].copy(),
                                   floor=self.group_floor_[cell_group], building=self.group_building_[cell_group],
                                   row_rp=np.zeros(0, dtype=int))
        self.rp_key_index_ = {k: i for i, k in enumerate(keys)}

    def reuse_choices(self, validated: FingerprintModel) -> None:
        """Take the length scale and k ``validated`` chose; calibration is the training step's."""
        if isinstance(validated, RadioMapModel):
            self.length_scale_m = validated.length_scale_m_
            self.k = validated.k_
            self.calibrate = False

    def _cross_validate(self, X: np.ndarray, data: TrainingData) -> None:
        """Held-out walks (devices) or reference points, ``CV_FOLDS`` folds, the floor taken
        as known: ``length_scale_m_`` and ``k_`` with the lowest mean error, and (when
        ``calibrate``) ``calibration_`` on their held-out fixes."""
        rng = np.random.default_rng(0)
        fs, row_rp = data.fs, data.rp.row_rp
        fold_rp = rng.permutation(len(data.rp)) % CV_FOLDS
        if fs.device is not None:
            names, device = np.unique(fs.device.astype(str), return_inverse=True)
            rp_device = np.full(len(data.rp), -1)
            rp_device[row_rp] = device
            if len(names) >= 3 and np.array_equal(rp_device[row_rp], device):  # each point surveyed by one walk
                fold_rp = (rng.permutation(len(names)) % CV_FOLDS)[rp_device]
        fold = fold_rp[row_rp]
        scales = self.length_grid if self.length_scale_m is None else (self.length_scale_m,)
        ks = self.k_grid if self.k is None else (self.k,)
        xy_rows = np.column_stack([fs.x, fs.y])
        errs = np.zeros((len(scales), len(ks)))
        res: dict[tuple[int, int], list[np.ndarray]] = {}
        covs: dict[tuple[int, int], list[np.ndarray]] = {}
        per_fold = max(1, self.cv_rows // CV_FOLDS)
        count = 0
        for f in range(CV_FOLDS):
            te, tr = np.flatnonzero(fold == f), np.flatnonzero(fold != f)
            if not len(te) or not len(tr):
                continue
            if len(te) > per_fold:
                te = np.sort(rng.choice(te, per_fold, replace=False))
            rps = np.unique(row_rp[tr])
            remap = np.full(len(data.rp), -1)
            remap[rps] = np.arange(len(rps))
            F, weight = self._rp_means(X[tr], remap[row_rp[tr]], len(rps))
            xy, group = data.rp.xy[rps], self.survey_group_[rps]
            te = te[np.isin(data.row_group[te], group)]  # a floor with no map left says nothing
            if not len(te):
                continue
            count += len(te)
            cols = np.flatnonzero((X[te] > 0).any(axis=0))  # the map where the held-out scans look
            for i, scale in enumerate(scales):
                cells, cell_group, GT, g_sum = self._map(xy, group, weight, F, scale, cols)
                D = self._distances(X[te][:, cols], GT, g_sum)
                D[cell_group[None, :] != data.row_group[te][:, None]] = np.inf
                order = nearest_columns(D, max(ks))
                for j, k in enumerate(ks):
                    with np.errstate(divide="ignore"):
                        pred = self._reduce_over(np.log(self._scores(D, k, self.weight_power, order)), cells,
                                                 cell_group)
                    r = pred.xy - xy_rows[te]
                    errs[i, j] += np.hypot(r[:, 0], r[:, 1]).sum()
                    res.setdefault((i, j), []).append(r)
                    covs.setdefault((i, j), []).append(pred.covariance)
        if not res:
            return
        flat = int(np.argmin(errs))
        best = (flat // len(ks), flat % len(ks))
        self.length_scale_m_, self.k_ = float(scales[best[0]]), int(ks[best[1]])
        self.cv_errors_ = (errs / count).round(3).tolist()  # mean error (m) per (length scale, k)
        if self.calibrate:
            self.calibration_ = fit_calibration(np.concatenate(res[best]), np.concatenate(covs[best]))

    # ---- queries -------------------------------------------------------------------------
    @staticmethod
    def _distances(Q: np.ndarray, GT: np.ndarray, g_sum: np.ndarray) -> np.ndarray:
        """(nq, c) Sørensen distances ``Σ|q−g| / Σ(q+g)`` from encoded queries to the cells,
        with ``Σ|q−g| = Σq + Σg − 2·Σ_{j heard by q} min(q_j, g_j)`` (one gather of the
        query's heard transmitters)."""
        Q = np.asarray(Q, dtype=np.float32)
        out = np.empty((len(Q), GT.shape[1]))
        for i, q in enumerate(Q):
            cols = np.flatnonzero(q > 0)
            qv = q[cols]
            inter = np.minimum(GT[cols], qv[:, None]).sum(axis=0)
            tot = float(qv.sum(dtype=np.float64)) + g_sum
            out[i] = (tot - 2.0 * inter) / np.maximum(tot, 1e-9)
        return out

    def _scores(self, D: np.ndarray, k: int, power: float, order: np.ndarray | None = None) -> np.ndarray:
        """(nq, c) weights 1/d^power of each query's k nearest cells (from ``order``, each
        row's nearest first, when given), 0 elsewhere."""
        idx = (nearest_columns(D, k) if order is None else order)[:, :k]
        d = np.take_along_axis(D, idx, axis=1)
        scores = np.zeros(D.shape)
        np.put_along_axis(scores, idx, np.where(np.isfinite(d), (d + 1e-6) ** -power, 0.0), axis=1)
        return scores

    def _reduce_over(self, logs: np.ndarray, cells: np.ndarray, cell_group: np.ndarray):
        """The posterior over ``cells`` (a candidate map of the cross-validation)."""
        return reduce_live(logs, cells, cell_group, self.group_floor_, self.group_building_, self.cov_floor_m_,
                           self.n_candidates)

    def _log_scores(self, Q, Hq, mask):
        D = self._distances(Q, self.GT_, self.g_sum_)
        if mask is not None:
            D = np.where(mask, D, np.inf)
        with np.errstate(divide="ignore"):
            return np.log(self._scores(D, self.k_, self.weight_power))
