"""Hierarchical weighted KNN ("wknn"): building → floor → position, fast NumPy path.

The model the UJIIndoorLoc study chose (docs/fingerprint-results.md), in three steps
per query, each over a float32 fingerprint matrix held densely in memory:

1. **Building**: the ``building_k`` nearest fingerprints vote (weights 1/d) for a
   building; everything after is restricted to it.
2. **Floor**: the ``floor_k`` nearest fingerprints *of that building* vote for a floor.
   A scan in building 1 therefore never answers a floor of building 0.
3. **Position**: the ``k`` nearest fingerprints *of that floor* give the posterior over
   reference points (weights 1/d); ``k=None`` picks k by cross-validation over
   held-out reference points of the training data.

The three steps are resolved from each query's ``CANDIDATES`` nearest fingerprints
(one partial sort), falling back to the full matrix when those hold too few of the
chosen building or floor, so the answer is exactly the full computation's.

**Coverage.** ``in_coverage``: a scan farther from every fingerprint than 99 % of the
internally held-out scans at unsurveyed reference points were (``coverage_threshold_``)
resembles nothing surveyed, and its fix is only "the nearest room". Both sides use the
same distance: to the nearest fingerprint of the whole site, *after* the per-query
offset estimate (so a phone's constant RSS offset does not push it out of coverage).
``locate_covered`` takes that distance from the query's own distance pass.

**Calibration.** The fix's covariance (the posterior's spread + ``cov_floor_m²``) goes
through ``calibration_`` (calibration.py), fitted at ``fit`` on internally held-out
fixes so a model used on its own is calibrated; the server's training step refits it
on its own held-out sample. ``calibrate="points"`` (default) holds out whole
reference points (a scan where nobody surveyed, chosen on UJIIndoorLoc's choosing
users), ``"rows"`` held-out scans at surveyed points, ``"mixed"`` both, None off.

Distances use the sparsity of a scan (it hears a few dozen of hundreds of
transmitters): with features ≥ 0 and 0 = not heard,

- ``sorensen`` (Bray–Curtis): ``Σ|q−f| / Σ(q+f)`` where
  ``Σ|q−f| = Σq + Σf − 2·Σ_{j heard by q} min(q_j, f_j)``;
- ``euclidean``: ``|q|² + |f|² − 2·q·f``;

so a query costs one gather of its heard columns, no scikit-learn call. The gather is
over an index of the fingerprints that hear each transmitter (``tx_ptr_``/``tx_rows_``/
``tx_vals_``, the stored matrix's nonzeros by transmitter): with Sørensen a fingerprint
hearing none of the query's transmitters is at distance exactly 1, the largest possible,
so one query's work is over the few thousand fingerprints sharing a transmitter with it
(its *candidates*), not the whole matrix; the full row is only built when the candidates
hold too few fingerprints for the hierarchy.

**Device offset.** ``offset_estimate`` (default): the phone's RSS offset is estimated
per query as the median difference (dB) between the query and its ``offset_neighbours``
nearest fingerprints over the transmitters both hear; the query is shifted by it and
matched again, ``offset_iterations`` times (each converges a little further: the first
neighbours of a shifted scan are biased towards the shift). ``offset_search_db``
(off by default): instead try shifts every ``offset_step_db`` within ±that and keep the
one whose nearest fingerprint matches best (one distance pass per shift). The estimate is
made only when the query shares at least ``offset_min_tx`` (8) transmitters with those
neighbours: with fewer, an offset cannot be told from a place (a scan of four APs shifted
by a few dB resembles another spot of the floor), and the estimate moves fixes along the
walk together. 8 was chosen on UJIIndoorLoc's choosing users (knn 10.35 → 10.32 m, wknn
9.88 → 9.89: real phones keep their estimate) and the simulator's stress split (four
transmitters: knn fixes' ekf 4.17 → 3.85 m); docs/fingerprint-results.md.

**Cleaning** at fit: exact duplicate rows (same place, same scan) are dropped and
transmitters heard by fewer than ``min_tx_rows`` fingerprints are ignored.
"""

from __future__ import annotations

from collections.abc import Mapping
from contextvars import ContextVar

import numpy as np

from server.estimation.types import Fix

from .base import FingerprintModel, TrainingData
from .calibration import fit_calibration
from .distance import nearest_columns, row_sums, weighted_vote

DISTANCES = ("sorensen", "euclidean")
CALIBRATIONS = ("rows", "points", "mixed", None)
CV_FOLDS = 5
#: held-out scans whose distances to a fold's map the cross-validation holds at once
CV_QUERY_BLOCK = 64

#: where ``_log_scores`` leaves each chunk's coverage distances while ``locate_covered`` waits for
#: them (a context variable: one model instance serves several threads at once)
_COVERAGE_SINK: ContextVar[list[np.ndarray] | None] = ContextVar("wknn_coverage_sink", default=None)


def _smallest(d: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` smallest values of the 1-D ``d``, in no order. Partitioned at two
    ranks (k−2, k−1): NumPy then runs its introselect, measured 4–7× faster on a query's
    few thousand distances than the vectorised select it runs for a single rank."""
    if k >= len(d):
        return np.arange(len(d))
    if k == 1:
        return np.array([np.argmin(d)])
    return np.argpartition(d, (k - 2, k - 1))[:k]


def _row_keys(X: np.ndarray, row_rp: np.ndarray, block: int = 8192) -> np.ndarray:
    """(n, 3) keys equal for equal (fingerprint, reference point) rows: two random projections
    of the row (float64, in blocks: memory stays O(n)) and the reference point. Different rows
    share both projections only by a coincidence of measure zero."""
    P = np.random.default_rng(20261201).standard_normal((X.shape[1], 2))
    out = np.empty((len(X), 3))
    for s in range(0, len(X), block):
        out[s: s + block, :2] = np.asarray(X[s: s + block], dtype=np.float64) @ P
    out[:, 2] = row_rp
    return out


class WKNNModel(FingerprintModel):
    """k: neighbours for the position (None = chosen by cross-validation among
    ``k_grid``); distance: "sorensen" or "euclidean"; building_k / floor_k: neighbours
    voting for building and floor; offset_search_db: half-width (dB) of the per-query
    offset search (0 = off); min_tx_rows: transmitters heard by fewer fingerprints are
    ignored; dedupe: drop exact duplicate fingerprints; offset_estimate: per-query RSS
    offset from the nearest ``offset_neighbours`` fingerprints (at most ±``offset_max_db``;
    made when they share at least ``offset_min_tx`` transmitters with the query);
    calibrate: "points", "rows", "mixed" or None — the held-out residuals ``calibration_``
    is fitted on (module docstring); cv_rows: held-out scans used by
    the cross-validation (k and calibration)."""

    name = "wknn"
    weights = "distance"  # neighbours weighted 1/d; knn.py's subclass may weigh them equally
    offset_min_tx = 1  # as models fitted before the parameter existed estimate the offset (instances: 8)
    CANDIDATES = 96  # nearest fingerprints per query the hierarchy is resolved from
    DERIVED = ("tx_ptr_", "tx_rows_", "tx_vals_", "tx_bounds_")  # rebuilt from XT_ at load, not stored

    def __init__(self, k: int | None = None, distance: str = "sorensen", building_k: int = 10,
                 floor_k: int = 10, offset_search_db: float = 0.0, offset_step_db: float = 3.0,
                 min_tx_rows: int = 2, dedupe: bool = True, k_grid: tuple[int, ...] = (1, 2, 3, 4, 5, 7, 9),
                 offset_estimate: bool = True, offset_neighbours: int = 10, offset_max_db: float = 15.0,
                 offset_iterations: int = 3, offset_min_tx: int = 8,
                 calibrate: str | None = "points", cv_rows: int = 1500,
                 missing: str = "exponential", floor_classifier: str | None = None, **common):
        super().__init__(missing=missing, floor_classifier=floor_classifier, **common)
        if distance not in DISTANCES:
            raise ValueError(f"distance must be one of {DISTANCES}")
        self.k = None if k is None else int(k)
        self.distance = distance
        self.building_k = int(building_k)
        self.floor_k = int(floor_k)
        self.offset_search_db = float(offset_search_db)
        self.offset_step_db = float(offset_step_db)
        self.min_tx_rows = int(min_tx_rows)
        self.dedupe = bool(dedupe)
        self.k_grid = tuple(int(v) for v in k_grid)
        if min((self.building_k, self.floor_k, *self.k_grid, *(() if self.k is None else (self.k,)))) < 1 \
                or not self.k_grid:
            raise ValueError("k, building_k, floor_k and every k_grid value must be at least 1 (k_grid not empty)")
        if calibrate not in CALIBRATIONS:
            raise ValueError(f"calibrate must be one of {CALIBRATIONS}")
        self.calibrate = calibrate
        self.cv_rows = int(cv_rows)
        self.offset_estimate = bool(offset_estimate)
        self.offset_neighbours = int(offset_neighbours)
        self.offset_max_db = float(offset_max_db)
        self.offset_iterations = int(offset_iterations)
        self.offset_min_tx = int(offset_min_tx)

    # ---- state (artifacts store the mostly-zero matrix sparse) ---------------------------
    def __getstate__(self) -> dict:
        from scipy import sparse

        state = {k: v for k, v in vars(self).items() if k not in self.DERIVED}
        if isinstance(state.get("XT_"), np.ndarray):
            state["XT_"] = sparse.csr_matrix(state["XT_"])
        return state

    def __setstate__(self, state: dict) -> None:
        from scipy import sparse

        state = dict(state)
        if sparse.issparse(state.get("XT_")):
            state["XT_"] = np.ascontiguousarray(state["XT_"].toarray(), dtype=np.float32)
        vars(self).update(state)
        if isinstance(state.get("XT_"), np.ndarray):
            self._index_transmitters()

    # ---- fit ---------------------------------------------------------------------------
    def _fit(self, X, H, data: TrainingData) -> None:
        X = np.asarray(X, dtype=np.float32)
        keep_rows = np.ones(len(X), dtype=bool)
        if self.dedupe and len(X):
            _, first = np.unique(_row_keys(X, data.rp.row_rp), axis=0, return_index=True)
            keep_rows[:] = False
            keep_rows[first] = True
        heard = (X[keep_rows] > 0).sum(axis=0)
        self.tx_active_ = heard >= max(self.min_tx_rows, 1)
        if not self.tx_active_.any():
            self.tx_active_ = heard > 0
        self._set_matrix(X, np.flatnonzero(keep_rows), None if H is None else H[keep_rows] * self.heading_weight_,
                         data.rp.row_rp[keep_rows], data.row_group[keep_rows])
        self.k_ = self.k if self.k is not None else 3
        self.coverage_threshold_ = getattr(self, "reused_coverage_threshold_", float("inf"))
        if self.k is None or self.calibrate is not None:
            self._cross_validate(data, keep_rows)

    def _typical_distance(self, X: np.ndarray, M: np.ndarray) -> float:
        """Sørensen's median: the heading feature is then weighed on the scale of the distance it
        is added to (a Euclidean spread of these features is ≈ 10× smaller, too small to count)."""
        if self.distance != "sorensen":
            return super()._typical_distance(X, M)
        return float(np.median(np.abs(X - M).sum(axis=1) / np.maximum((X + M).sum(axis=1), 1e-9)))

    def _set_matrix(self, X, rows, H, row_rp, row_group, block: int = 8192) -> None:
        """Store fingerprints ``X[rows]`` as the (m, n) matrix (a transmitter's readings
        contiguous), copied in blocks of rows so no second (n, m) copy is ever made."""
        XT = np.empty((X.shape[1], len(rows)), dtype=np.float32)
        for s in range(0, len(rows), block):
            XT[:, s: s + block] = X[rows[s: s + block]].T
        XT *= self.tx_active_[:, None]
        self._set_columns(XT, H, row_rp, row_group)

    def _set_columns(self, XT, H, row_rp, row_group) -> None:
        """Store an (m, n) matrix already in stored form (the cross-validation's folds are its columns)."""
        self.XT_ = XT
        self.x_sum_ = XT.sum(axis=0, dtype=np.float64)
        self.x_sq_ = np.einsum("ji,ji->i", XT, XT, dtype=np.float64)
        self.H_ = None if H is None else np.asarray(H, dtype=np.float32)  # already weighted
        self.row_rp_ = np.asarray(row_rp, dtype=np.int64)
        self.row_group_ = np.asarray(row_group, dtype=np.int64)
        self.row_building_ = self.group_building_[self.row_group_] if len(self.row_group_) else self.row_group_
        self._index_transmitters()

    def _index_transmitters(self) -> None:
        """``XT_``'s nonzeros by transmitter: the fingerprints hearing transmitter j are
        ``tx_rows_[tx_ptr_[j]: tx_ptr_[j + 1]]`` (ascending), their features ``tx_vals_`` alike
        (float32 as stored, rows int32 where they fit: ≈ 3 MB for UJIIndoorLoc, half the memory
        a query streams through; ``tx_bounds_``: ``tx_ptr_`` as Python ints, sliced without boxing)."""
        tx, rows = np.nonzero(self.XT_)
        self.tx_ptr_ = np.concatenate([[0], np.cumsum(np.bincount(tx, minlength=self.XT_.shape[0]))])
        self.tx_rows_ = rows.astype(np.int32) if self.XT_.shape[1] < 2**31 else rows
        self.tx_vals_ = np.ascontiguousarray(self.XT_[tx, rows], dtype=np.float32)
        self.tx_bounds_ = self.tx_ptr_.tolist()

    def reuse_choices(self, validated: FingerprintModel) -> None:
        """Take k and the coverage threshold ``validated`` chose by cross-validation and
        skip choosing them again (calibration is the training step's)."""
        if isinstance(validated, WKNNModel):
            self.k = validated.k_
            self.calibrate = None
            self.reused_coverage_threshold_ = validated.coverage_threshold_

    def _cross_validate(self, data: TrainingData, keep_rows: np.ndarray) -> None:
        """Internal 5-fold cross-validation (the floor taken as known).

        ``k_`` (when ``k`` is None): the grid value with the lowest mean error over
        held-out *reference points* (all their scans out of the map): a walker's scan is
        usually taken between surveyed points, which is what this mimics.

        ``calibration_`` (when ``calibrate``): fitted on the held-out fixes (raw
        covariance) — at held-out reference points ("points"), on held-out scans
        (users, else devices, else random rows) at reference points that stay in the map
        ("rows"), or on both pooled ("mixed")."""
        n = int(keep_rows.sum())
        rng = np.random.default_rng(0)
        n_rp = int(self.row_rp_.max()) + 1 if n else 0
        fold_rp = (rng.permutation(n_rp) % CV_FOLDS)[self.row_rp_]
        grid = self.k_grid if self.k is None else (self.k,)
        errs, held_rp, count, nearest = self._cv_pass(fold_rp, grid, rng, coverage=True)
        if count == 0:
            return
        self.coverage_threshold_ = float(np.quantile(nearest, 0.99))  # module docstring: Coverage
        self.k_cv_errors_ = (errs / count).tolist()
        best = int(np.argmin(errs))
        self.k_ = int(grid[best])
        if self.calibrate is None:
            return
        parts = [held_rp[best]] if self.calibrate in ("points", "mixed") else []
        if self.calibrate in ("rows", "mixed"):
            parts.append(self._row_pass(data.fs.subset(keep_rows), rng)[0])  # a copy only when asked
        self.calibration_ = fit_calibration(np.concatenate([r for r, _ in parts]),
                                            np.concatenate([c for _, c in parts]))

    def _row_pass(self, fs, rng) -> list[tuple[np.ndarray, np.ndarray]]:
        n = len(fs)
        groups = fs.user if fs.user is not None else fs.device
        if groups is not None and len(set(groups.astype(str))) >= 3:
            names = np.unique(groups.astype(str))
            fold_of = {g: i % CV_FOLDS for i, g in enumerate(rng.permutation(names))}
            fold_row = np.array([fold_of[g] for g in groups.astype(str)])
        else:
            fold_row = rng.integers(0, CV_FOLDS, n)
        return self._cv_pass(fold_row, (self.k_,), rng)[1]

    def _cv_pass(self, fold: np.ndarray, grid, rng, coverage: bool = False
                 ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]], int, np.ndarray]:
        """Sum of errors per k over the folds, the residuals and raw covariances of the
        held-out fixes per k, the count of held-out scans, and (``coverage``) each held-out
        scan's coverage distance (``_coverage_distance``, as a query's) to its fold's map."""
        XT_all, H_all = self.XT_, self.H_  # folds are column subsets: one fold's copy at a time
        rp_all, grp_all = self.row_rp_, self.row_group_
        errs = np.zeros(len(grid))
        res: list[list[np.ndarray]] = [[] for _ in grid]
        covs: list[list[np.ndarray]] = [[] for _ in grid]
        nearest: list[float] = []
        count = 0
        try:
            for f in range(CV_FOLDS):
                te = np.flatnonzero(fold == f)
                tr = np.flatnonzero(fold != f)
                if len(te) == 0 or len(tr) == 0:
                    continue
                if len(te) > self.cv_rows // CV_FOLDS:
                    te = np.sort(rng.choice(te, self.cv_rows // CV_FOLDS, replace=False))
                self._set_columns(XT_all[:, tr], None if H_all is None else H_all[tr], rp_all[tr], grp_all[tr])
                Hq = None if H_all is None else H_all[te] / max(self.heading_weight_, 1e-12)
                Q = XT_all[:, te].T
                if coverage:
                    nearest.extend(self._coverage_distance(*self._offset_query(q, None if Hq is None else Hq[i]))
                                   for i, q in enumerate(Q))
                for c0 in range(0, len(te), CV_QUERY_BLOCK):  # D is (queries, fingerprints): a block at a time
                    tq = te[c0: c0 + CV_QUERY_BLOCK]
                    D = self._distances(Q[c0: c0 + CV_QUERY_BLOCK], None if Hq is None else Hq[c0: c0 + CV_QUERY_BLOCK])
                    D[self.row_group_[None, :] != grp_all[tq][:, None]] = np.inf  # in place: D is large
                    ok = np.isfinite(D).any(axis=1)  # a floor with no map left says nothing
                    D, tq = D[ok], tq[ok]
                    if not len(tq):
                        continue
                    truth = self.rp_xy_[rp_all[tq]]
                    order = nearest_columns(D, max(grid))
                    for i, k in enumerate(grid):
                        with np.errstate(divide="ignore"):
                            pred = self._reduce(np.log(self._scores(D, k, order)))
                        r = pred.xy - truth
                        errs[i] += np.hypot(*r.T).sum()
                        res[i].append(r)
                        covs[i].append(pred.covariance)
                    count += len(tq)
        finally:
            self._set_columns(XT_all, H_all, rp_all, grp_all)
        held = [(np.concatenate(r) if r else np.zeros((0, 2)), np.concatenate(c) if c else np.zeros((0, 2, 2)))
                for r, c in zip(res, covs, strict=True)]
        return errs, held, count, np.array(nearest)

    # ---- distances ---------------------------------------------------------------------
    def _intersections(self, cols: np.ndarray, qv: np.ndarray) -> np.ndarray:
        """(n,) ``Σ_j min(q_j, f_j)`` over the query's heard columns ``cols`` (values ``qv``,
        float32) for every stored fingerprint, accumulated in float64 in column order (the
        same sums, bit for bit, as a dense sum over the gathered rows), from the transmitter
        index only: one slice per heard transmitter. (The minimum of two float32 values is
        one of them: taken in float32, then summed in float64, it is the same sum.)"""
        ptr, rows, vals = self.tx_bounds_, self.tx_rows_, self.tx_vals_
        spans = [(ptr[j], ptr[j + 1]) for j in cols.tolist()]
        if not spans:
            return np.zeros(self.XT_.shape[1])
        w = np.concatenate([vals[a:b] for a, b in spans])  # one gather, then one minimum over it
        np.minimum(w, np.repeat(np.asarray(qv, dtype=np.float32), [b - a for a, b in spans]), out=w)
        return np.bincount(np.concatenate([rows[a:b] for a, b in spans]), weights=w, minlength=self.XT_.shape[1])

    def _distances(self, Q: np.ndarray, Hq: np.ndarray | None) -> np.ndarray:
        """(nq, n) distances from encoded queries to the stored fingerprints."""
        Q = np.asarray(Q, dtype=np.float32) * self.tx_active_[None, :]
        out = np.empty((len(Q), self.XT_.shape[1]), dtype=np.float64)
        for i, q in enumerate(Q):
            cols = np.flatnonzero(q > 0)
            qv = q[cols]
            if self.distance == "sorensen":
                tot = float(qv.sum()) + self.x_sum_
                d = (tot - 2.0 * self._intersections(cols, qv)) / np.maximum(tot, 1e-9)
            else:
                cross = qv @ self.XT_[cols]
                d = np.sqrt(np.maximum(float(qv @ qv) + self.x_sq_ - 2.0 * cross, 0.0))
            out[i] = d
        if self.H_ is not None and Hq is not None:
            hq = np.asarray(Hq, dtype=np.float32) * self.heading_weight_
            dh = ((hq[:, None, :] - self.H_[None, :, :]) ** 2).sum(-1)
            out += np.sqrt(dh)
        return out

    def _query_distances(self, q: np.ndarray, hq: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """One encoded query's distances as (candidates, their distances): every stored
        fingerprint outside the candidates is at distance exactly 1 (Sørensen: it hears
        none of the query's transmitters), the farthest possible. Euclidean distance,
        headings, or a query hearing no active transmitter: every fingerprint is a candidate."""
        q = np.asarray(q, dtype=np.float32) * self.tx_active_
        cols = np.flatnonzero(q > 0)
        if self.distance != "sorensen" or (hq is not None and self.H_ is not None) or not len(cols):
            return np.arange(self.XT_.shape[1]), self._distances(q[None], None if hq is None else hq[None])[0]
        qv = q[cols]
        inter = self._intersections(cols, qv)
        cand = np.flatnonzero(inter > 0)  # (a boolean's nonzeros: ≈ 4× faster than a float array's)
        q_sum = float(qv.sum())
        tot = q_sum + self.x_sum_[cand]
        d = inter[cand]  # (tot − 2·inter) / tot, in place: the same operations, no temporaries
        d *= -2.0
        d += tot
        d /= tot if q_sum >= 1e-9 else np.maximum(tot, 1e-9)  # tot ≥ q_sum: the floor only guards an empty sum
        return cand, d

    def _full_row(self, cand: np.ndarray, d: np.ndarray) -> np.ndarray:
        """``_query_distances``' answer as the (n,) row over every fingerprint."""
        row = np.ones(self.XT_.shape[1])
        row[cand] = d
        return row

    def _coverage_distance(self, cand: np.ndarray, d: np.ndarray, near: np.ndarray | None = None) -> float:
        """Distance to the nearest stored fingerprint (inf when none is stored); ``near``: ``d``'s
        nearest as ``_sorted_nearest`` gives them, when known (the first is the minimum)."""
        low = float(d[near[0]]) if near is not None else float(d.min()) if len(d) else np.inf
        return min(low, 1.0) if len(cand) < self.XT_.shape[1] else low

    def _sorted_nearest(self, d: np.ndarray) -> np.ndarray | None:
        """Indices of the ``_hierarchy_m()`` smallest of one query's distances ``d``, nearest first,
        as ``_query_scores`` picks them (None when it takes the full row instead). The offset
        estimate takes its nearest from them too: one partial sort per distance pass, not two."""
        m = self._hierarchy_m()
        if m < self.XT_.shape[1] and np.count_nonzero(np.isfinite(d)) >= m:
            near = _smallest(d, m)
            return near[np.argsort(d[near])]
        return None

    def _shifted(self, R: np.ndarray, delta: float) -> np.ndarray:
        return self.encoder_.transform(R + delta)

    def _estimate_offset(self, q: np.ndarray, cand: np.ndarray, d: np.ndarray, near: np.ndarray | None = None) -> float:
        """One query's RSS offset (dB): the median, over the transmitters heard both by the
        query and by its ``offset_neighbours`` nearest fingerprints, of (fingerprint −
        query); 0 when fewer than 3 such readings. (The nearest are among the candidates:
        a non-candidate hears none of the query's transmitters and adds no reading.)
        ``near``: ``d``'s nearest first (``_sorted_nearest``), when known: their first k are
        the k nearest whenever the k-th is strictly nearer than the next (the median does
        not depend on their order); on a tie there, the partial sort picks as it always did."""
        k = max(1, min(self.offset_neighbours, self.XT_.shape[1]))
        if near is not None and k < len(near) and d[near[k - 1]] < d[near[k]]:
            nearest = cand[near[:k]]
        else:
            nearest = cand[_smallest(d, k)]
        cols = np.flatnonzero(q > 0)  # the heard readings alone: the others decode to NaN
        readings = np.empty((len(cols), len(nearest) + 1), dtype=np.float32)  # the neighbours', then the query's
        readings[:, :-1] = self.XT_[cols[:, None], nearest]
        readings[:, -1] = q[cols]
        dbm = self.encoder_.decode(readings)  # one decode (element by element) for both
        diff = dbm[:, :-1] - dbm[:, -1:]
        both = ~np.isnan(diff)
        if int(both.any(axis=1).sum()) < self.offset_min_tx:
            return 0.0
        diff = np.sort(diff[both])
        n = len(diff)
        if n < 3:
            return 0.0
        # the median as np.median computes it (the middle value, or the mean of the two middle ones)
        median = float(diff[n // 2]) if n % 2 else (float(diff[n // 2 - 1]) + float(diff[n // 2])) / 2.0
        return max(-self.offset_max_db, min(median, self.offset_max_db))

    def _offset_query(self, q: np.ndarray, hq: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """``_query_distances`` with the per-query RSS offset (see the module docstring)."""
        cand, d, _ = self._offset_query_nearest(q, hq)
        return cand, d

    def _offset_query_nearest(self, q: np.ndarray, hq: np.ndarray | None
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``_offset_query``, and the answer's nearest first (``_sorted_nearest``) when they were
        picked on the way (else None)."""
        cand, d = self._query_distances(q, hq)
        near = None
        if self.offset_estimate:
            r0 = None
            total, qs = 0.0, q
            for _ in range(self.offset_iterations):
                near = self._sorted_nearest(d)
                delta = self._estimate_offset(qs, cand, d, near)
                if abs(delta) < 0.5:
                    break
                if r0 is None:
                    r0 = self.encoder_.decode(q[None])
                total = max(-self.offset_max_db, min(total + delta, self.offset_max_db))
                qs = self.encoder_.transform(r0 + total)[0]
                cand, d = self._query_distances(qs, hq)
                near = None
        if self.offset_search_db <= 0:
            return cand, d, near
        r = self.encoder_.decode(q[None])
        best = self._coverage_distance(cand, d)
        steps = np.arange(self.offset_step_db, self.offset_search_db + 1e-9, self.offset_step_db)
        for delta in np.concatenate([steps, -steps]):
            c2, d2 = self._query_distances(self._shifted(r, float(delta))[0], hq)
            m = self._coverage_distance(c2, d2)
            if m < best:
                cand, d, best = c2, d2, m
        return cand, d, None

    # ---- hierarchy ---------------------------------------------------------------------
    def _restrict(self, D: np.ndarray) -> np.ndarray:
        """Building, then floor: distances outside the chosen (building, floor) → inf."""
        if len(self.group_floor_) <= 1:
            return D
        buildings = np.unique(self.group_building_)
        if len(buildings) > 1:
            b_index = np.searchsorted(buildings, self.row_building_)
            b = buildings[weighted_vote(D, b_index, self.building_k, len(buildings))]
            D = np.where(self.row_building_[None, :] == b[:, None], D, np.inf)
        g = weighted_vote(D, self.row_group_, self.floor_k, len(self.group_floor_))
        return np.where(self.row_group_[None, :] == g[:, None], D, np.inf)

    def _scores(self, D: np.ndarray, k: int, order: np.ndarray | None = None) -> np.ndarray:
        idx = (nearest_columns(D, k) if order is None else order)[:, :k]
        d = np.take_along_axis(D, idx, axis=1)
        return row_sums(self.row_rp_[idx], self._neighbour_weights(d), len(self.rp_xy_))

    def _neighbour_weights(self, d: np.ndarray) -> np.ndarray:
        """The position's weight of neighbours at distances ``d`` (0 for an infinite one)."""
        if self.weights == "uniform":
            return np.where(np.isfinite(d), 1.0, 0.0)
        return np.where(np.isfinite(d), 1.0 / (d + 1e-6), 0.0)

    def coverage(self, rss) -> tuple[np.ndarray, np.ndarray]:
        """(coverage distance, in-coverage flag) per scan — rss as ``predict`` takes it: the
        distance to the nearest fingerprint after the offset estimate, and whether it is
        within ``coverage_threshold_`` (module docstring: Coverage)."""
        self._check_fitted()
        Q = self.encoder_.transform(self._as_matrix(rss))
        Hq = self._headings(None, len(Q))
        nearest = np.array([self._coverage_distance(*self._offset_query(q, None if Hq is None else Hq[i]))
                            for i, q in enumerate(Q)])
        return nearest, nearest <= self.coverage_threshold_

    def locate_covered(self, rss: Mapping[str, float], heading_deg: float | None = None) -> tuple[Fix, float]:
        """``locate`` and the scan's coverage distance (as ``coverage``), from one distance pass."""
        sink: list[np.ndarray] = []
        token = _COVERAGE_SINK.set(sink)
        try:
            fix = self.locate(rss, heading_deg)
        finally:
            _COVERAGE_SINK.reset(token)
        return fix, float(sink[0][0])

    def _hierarchy_m(self) -> int:
        return min(self.XT_.shape[1], max(self.CANDIDATES, self.building_k, self.floor_k, self.k_))

    def _hierarchy_scores(self, D: np.ndarray) -> np.ndarray:
        """``_scores(_restrict(D), k_)`` from the ``CANDIDATES`` nearest fingerprints of
        each query (one partial sort instead of three): exact, because the nearest
        fingerprints of the chosen building (floor) are the first of that building
        (floor) among the query's nearest overall; a query whose candidates hold too
        few of them takes the full path."""
        n, n_rows = D.shape
        m = self._hierarchy_m()
        if m >= n_rows:
            return self._scores(self._restrict(D), self.k_)
        order = nearest_columns(D, m)
        dist = np.take_along_axis(D, order, axis=1)
        scores = np.zeros((n, len(self.rp_xy_)))
        for i in range(n):
            row = self._resolve(order[i], dist[i])
            scores[i] = self._scores(self._restrict(D[i: i + 1]), self.k_)[0] if row is None else row
        return scores

    def _resolve(self, o: np.ndarray, d: np.ndarray) -> np.ndarray | None:
        """One query's scores over reference points from its nearest fingerprints ``o``
        (distances ``d``, ascending): building, floor, then the ``k_`` nearest of that
        floor; None when they hold too few of the chosen building or floor."""
        ok = np.isfinite(d)
        o, d = o[ok], d[ok]
        if len(self.group_floor_) > 1:
            if self.group_building_.min() != self.group_building_.max():
                b = self._vote_small(self.row_building_[o[: self.building_k]], d[: self.building_k])
                keep = self.row_building_[o] == b
                if keep.sum() < max(self.floor_k, self.k_):
                    return None
                o, d = o[keep], d[keep]
            g = self._vote_small(self.row_group_[o[: self.floor_k]], d[: self.floor_k])
            keep = self.row_group_[o] == g
            if keep.sum() < self.k_:
                return None
            o, d = o[keep], d[keep]
        o, d = o[: self.k_], d[: self.k_]
        scores = np.zeros(len(self.rp_xy_))
        np.add.at(scores, self.row_rp_[o], self._neighbour_weights(d))
        return scores

    def _query_scores(self, cand: np.ndarray, d: np.ndarray, mask: np.ndarray | None,
                      near: np.ndarray | None = None) -> np.ndarray:
        """``_hierarchy_scores`` of one query given as ``_query_distances`` (candidates and
        their distances; ``mask`` over reference points): from the candidates alone when
        at least ``_hierarchy_m()`` of them are allowed (the nearest fingerprints are
        then all candidates), else on the full row. ``near``: ``_sorted_nearest(d)``, when
        known (only without ``mask``)."""
        if mask is not None:
            d = np.where(mask[self.row_rp_[cand]], d, np.inf)
            near = None
        if near is None:
            near = self._sorted_nearest(d)
        if near is not None:
            row = self._resolve(cand[near], d[near])
            if row is not None:
                return row
        full = self._full_row(cand, d)
        if mask is not None:
            full[~mask[self.row_rp_]] = np.inf
        return self._hierarchy_scores(full[None])[0]

    @staticmethod
    def _vote_small(labels: np.ndarray, d: np.ndarray):
        """The label (an integer) with the largest sum of 1/d weights (ties: the smallest
        label, as argmax over a vote table does)."""
        low = labels.min()
        return low + int(np.argmax(np.bincount(labels - low, weights=1.0 / (d + 1e-6))))

    def _log_scores(self, Q, Hq, mask):
        """Per query: offset-corrected distances over its candidates, then the hierarchy;
        each query's coverage distance goes to ``locate_covered`` when it waits for it."""
        scores = np.zeros((len(Q), len(self.rp_xy_)))
        nearest = np.empty(len(Q))
        for i, q in enumerate(Q):
            cand, d, near = self._offset_query_nearest(q, None if Hq is None else Hq[i])
            nearest[i] = self._coverage_distance(cand, d, near)
            scores[i] = self._query_scores(cand, d, None if mask is None else mask[i], near)
        sink = _COVERAGE_SINK.get()
        if sink is not None:
            sink.append(nearest)
        with np.errstate(divide="ignore"):
            return np.log(scores)
