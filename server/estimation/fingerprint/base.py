"""The common shape of every fingerprint model (scikit-learn style).

    model = KNNModel(k=3, kinds=["wifi"], use_heading=True).fit(fingerprint_set)
    fix = model.locate({"wifi:wap001": -67.0, ...}, heading_deg=90.0)   # -> Fix
    fixes = model.locate_many(list_of_scans, headings)                 # -> list[Fix]
    pred = model.predict(rss_matrix, headings)                          # -> Prediction (arrays)

Subclasses implement ``_fit(X, H, data)`` and ``_log_scores(Q, Hq, mask)`` returning
(nq, n_rp) log-scores over reference points; this class does the rest: transmitter
filtering by kind, missing-value representation, heading features, the floor-first
reduction to a `Fix`, and spatial restriction around a previous estimate.
Serialisation is artifact.py's (`to_bytes(model)` / `from_bytes(blob)`).
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Self

import numpy as np

from server.estimation.types import Candidate, Fix

from .calibration import IDENTITY, CovarianceCalibration
from .dataset import FingerprintSet, ReferencePoints
from .distance import weighted_vote
from .features import RssEncoder, heading_features
from .posterior import Prediction, reduce_live

#: fingerprints an SVC / extra-trees floor classifier is fitted on at most (chosen on
#: UJIIndoorLoc's choosing users: benchmarks/floor_classifier_scale.py)
FLOOR_CLASSIFIER_ROWS = 4000
#: values of ``floor_classifier`` (benchmarks/floor_classifier_choice.py compares them)
FLOOR_CLASSIFIERS = (None, "svc", "trees", "knn", "knn-svc")


def restricted(logs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(nq, n_rp) log-scores with the reference points outside ``mask`` at −inf, row by row; a row
    the mask would leave with nothing finite keeps all its scores (the restriction is ignored)."""
    masked = np.where(mask, logs, -np.inf)
    dead = np.asarray(~np.isfinite(masked).any(axis=1))
    return np.where(dead[:, None], logs, masked)


def stratified_rows(group: np.ndarray, cap: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``cap`` rows, each group keeping its share of them (at
    least one row), drawn at random within it; every row when there are few enough."""
    n = len(group)
    if n <= cap:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    _, inv, counts = np.unique(group, return_inverse=True, return_counts=True)
    inv = np.asarray(inv).reshape(-1)
    quota = np.minimum(counts, np.maximum(1, np.floor(counts * cap / n).astype(int)))
    return np.sort(np.concatenate([rng.choice(np.flatnonzero(inv == g), size=int(q), replace=False)
                                   for g, q in enumerate(quota)]))


class FloorKNN:
    """(building, floor) of a scan by its nearest reference points, building first.

    Features: exponential RSS (``RssEncoder("exponential")``), each scan divided by its
    sum. A constant dB offset multiplies exponential features by one factor, so the
    normalised scan does not depend on the phone's offset (only readings pushed across
    ``floor_dbm`` change it). Each reference point is the mean of its fingerprints:
    fitting is one pass over the rows (O(n)) and a query costs O(reference points × heard
    transmitters) whatever the number of fingerprints. Distance: Bray–Curtis (Sørensen).

    Building: the ``k`` nearest reference points vote (weights 1/d; k = 3 and the
    normalisation chosen on UJIIndoorLoc's choosing users, against k = 1, 5, 10, rows
    instead of means, powed features, Euclidean distance). Floor: the ``k``
    nearest of that building vote; or, when ``fit`` is given a fitted RBF SVC over the
    groups, that SVC's one-vs-one vote over the pairs of the building's groups (its
    ``predict`` when the site has one building), computed here in NumPy from its support
    vectors (one sparse kernel product per batch, no scikit-learn call per query). Either way a
    scan in building 1 never gets a floor of building 0.

    ``predict`` takes the model's floor design (its encoded RSS in the first ``n_rss``
    columns, heading columns after them, which only the SVC uses) and returns group indices.
    """

    BLOCK = 1024  # queries per kernel product (bounded memory)
    SPARSE_STATE = {"MT_": np.float32, "sv_": np.float64}  # mostly-zero matrices, stored sparse

    def __init__(self, input_encoder: RssEncoder, n_rss: int, k: int = 3):
        self.input_encoder = input_encoder
        self.n_rss = int(n_rss)
        self.k = int(k)
        self.encoder = RssEncoder("exponential", input_encoder.floor_dbm)

    def __getstate__(self) -> dict:
        """Artifacts store the reference-point means and the support vectors sparse."""
        from scipy import sparse

        state = dict(vars(self))
        for key in self.SPARSE_STATE:
            if isinstance(state.get(key), np.ndarray):
                state[key] = sparse.csr_matrix(state[key])
        return state

    def __setstate__(self, state: dict) -> None:
        from scipy import sparse

        state = dict(state)
        for key, dtype in self.SPARSE_STATE.items():
            if sparse.issparse(state.get(key)):
                state[key] = np.ascontiguousarray(state[key].toarray(), dtype=dtype)
        vars(self).update(state)

    def _features(self, design: np.ndarray) -> np.ndarray:
        V = self.encoder.transform(self.input_encoder.decode(np.asarray(design)[:, : self.n_rss]))
        return V / np.maximum(V.sum(axis=1, keepdims=True), np.float32(1e-12))

    def fit(self, design: np.ndarray, row_rp: np.ndarray, rp_group: np.ndarray, group_building: np.ndarray,
            svc=None) -> Self:
        """design: (n, ≥ n_rss) rows; row_rp: each row's reference point; rp_group: each
        reference point's (building, floor) group; group_building: each group's building;
        svc: an optional fitted sklearn RBF SVC over group indices (only its support
        vectors, coefficients and intercepts are kept)."""
        from scipy import sparse

        n_rp, n = len(rp_group), len(row_rp)
        means = np.zeros((n_rp, self.n_rss))
        for s in range(0, n, 4096):  # in blocks: bounded temporaries
            rows = np.arange(s, min(s + 4096, n))
            member = sparse.csr_matrix((np.ones(len(rows)), (row_rp[rows], rows - s)), shape=(n_rp, len(rows)))
            means += member @ self._features(design[rows]).astype(np.float64)
        means /= np.maximum(np.bincount(row_rp, minlength=n_rp), 1)[:, None]
        self.MT_ = np.ascontiguousarray(means.T, dtype=np.float32)  # (m, n_rp): a transmitter's column contiguous
        self.m_sum_ = self.MT_.sum(axis=0, dtype=np.float64)
        self.rp_group_ = np.asarray(rp_group, dtype=np.int64)
        self.group_building_ = np.asarray(group_building)
        self.rp_building_ = self.group_building_[self.rp_group_]
        self.sv_: np.ndarray | None = None
        if svc is not None:
            self._keep_svc(svc)
        return self

    def _keep_svc(self, svc) -> None:
        """libsvm's one-vs-one decision for classes i < j is Σ_{SV of i} α_{j−1} K +
        Σ_{SV of j} α_i K + b, positive = a vote for i: one (support vectors × pairs)
        coefficient matrix turns the kernel row into every pair's decision."""
        start = np.concatenate([[0], np.cumsum(svc.n_support_)])
        pairs = [(i, j) for i in range(len(svc.classes_)) for j in range(i + 1, len(svc.classes_))]
        coef = np.asarray(svc._dual_coef_)  # libsvm's signs (dual_coef_ flips them for two classes)
        W = np.zeros((len(svc.support_vectors_), len(pairs)))
        for p, (i, j) in enumerate(pairs):
            W[start[i]: start[i + 1], p] = coef[j - 1, start[i]: start[i + 1]]
            W[start[j]: start[j + 1], p] = coef[i, start[j]: start[j + 1]]
        sv = np.asarray(svc.support_vectors_, dtype=np.float64)
        self.sv_ = np.ascontiguousarray(sv.T)  # (features, support vectors): a feature's row contiguous
        self.sv_sq_ = (sv**2).sum(axis=1)
        self.gamma_ = float(svc._gamma)
        self.pair_coef_, self.pair_b_ = W, np.asarray(svc._intercept_, dtype=np.float64)
        classes = np.asarray(svc.classes_, dtype=np.int64)
        self.pair_i_ = classes[[i for i, _ in pairs]]
        self.pair_j_ = classes[[j for _, j in pairs]]

    def distances(self, design: np.ndarray) -> np.ndarray:
        """(nq, n_rp) Bray–Curtis distances from scans to the reference points."""
        V = self._features(design)
        out = np.ones((len(V), self.MT_.shape[1]))
        for i, q in enumerate(V):
            cols = np.flatnonzero(q > 0)
            if len(cols):
                qv = q[cols]
                inter = np.minimum(self.MT_[cols], qv[:, None]).sum(axis=0, dtype=np.float64)
                tot = float(qv.sum()) + self.m_sum_
                out[i] = (tot - 2.0 * inter) / np.maximum(tot, 1e-12)
        return out

    def _vote(self, D: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Per row, the label of the ``k`` nearest finite columns with the largest 1/d sum."""
        values, inv = np.unique(labels, return_inverse=True)
        return values[weighted_vote(D, np.asarray(inv).reshape(-1), self.k, len(values))]

    def svc_groups(self, design: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        """Per query, the group with the most one-vs-one votes of the SVC over the pairs of
        ``allowed`` (nq, groups) groups (ties: the lower index, as libsvm); a query whose
        allowed groups the SVC never saw gets its first allowed group."""
        from scipy import sparse

        sv = self.sv_
        assert sv is not None, "svc_groups needs the SVC (fit with svc=)"
        X = np.asarray(design, dtype=np.float64)
        n_groups = allowed.shape[1]
        to_i = np.zeros((len(self.pair_i_), n_groups))
        to_i[np.arange(len(self.pair_i_)), self.pair_i_] = 1.0
        to_j = np.zeros_like(to_i)
        to_j[np.arange(len(self.pair_j_)), self.pair_j_] = 1.0
        out = np.empty(len(X), dtype=np.int64)
        for s in range(0, len(X), self.BLOCK):
            x, ok = X[s: s + self.BLOCK], allowed[s: s + self.BLOCK]
            if len(x) == 1:  # one scan (a session's fix): a dense product over the columns it hears
                heard = np.flatnonzero(x[0])
                cross = x[:, heard] @ sv[heard]
            else:  # a scan hears few transmitters: one sparse product for the block
                cross = np.asarray(sparse.csr_matrix(x) @ sv)
            d2 = (x**2).sum(axis=1)[:, None] + self.sv_sq_[None, :] - 2.0 * cross
            dec = np.exp(-self.gamma_ * np.maximum(d2, 0.0)) @ self.pair_coef_ + self.pair_b_
            both = ok[:, self.pair_i_] & ok[:, self.pair_j_]
            votes = ((dec > 0) & both) @ to_i + ((dec <= 0) & both) @ to_j
            out[s: s + self.BLOCK] = np.argmax(np.where(ok, votes, -np.inf), axis=1)
        return out

    def predict(self, design: np.ndarray) -> np.ndarray:
        design = np.atleast_2d(design)
        if not len(design):
            return np.zeros(0, dtype=np.int64)
        one_building = len(set(self.group_building_.tolist())) == 1
        if one_building and self.sv_ is not None:  # no building to vote for: the SVC needs no distances
            return self.svc_groups(design, np.ones((len(design), len(self.group_building_)), dtype=bool))
        D = self.distances(design)
        b = np.full(len(D), self.group_building_[0]) if one_building else self._vote(D, self.rp_building_)
        in_b = self.group_building_[None, :] == b[:, None]  # (nq, groups)
        if self.sv_ is None:
            return self._vote(np.where(in_b[:, self.rp_group_], D, np.inf), self.rp_group_)
        return self.svc_groups(design, in_b)


class UnknownTransmittersError(ValueError):
    """The scan contains no transmitter known to the model (API: 422)."""


class NotFittedError(RuntimeError):
    pass


@dataclass
class TrainingData:
    """What ``_fit`` gets besides the feature matrices."""

    fs: FingerprintSet  # kinds-filtered, empty rows dropped
    rp: ReferencePoints
    row_group: np.ndarray  # (n,) group index of each fingerprint


def _near_array(near, n: int) -> np.ndarray | None:
    """``near`` as (n, 3) [x, y, floor or NaN]; accepts a Fix, a tuple or an array."""
    if near is None:
        return None
    if isinstance(near, Fix):
        near = (near.x, near.y, near.floor)
    a = np.asarray(near, dtype=float)
    if a.ndim == 1:
        a = np.tile(a, (n, 1))
    if a.shape[1] == 2:
        a = np.column_stack([a, np.full(len(a), np.nan)])
    return a


class FingerprintModel:
    """Base class. Common parameters:

    kinds: ["wifi"], ["ble"] or None (= all) — transmitters used, by id prefix.
    use_heading: add the walking heading as a feature (sin/cos).
    missing: "floor" (default) or "powed" — representation of not-heard transmitters
        (see features.py; "floor" measured better on UJIIndoorLoc).
    floor_dbm: the floor value / weakest reading kept (default −110 dBm).
    heading_weight: scale of the heading feature against RSS features; None = auto
        (half the typical RSS distance between scans of one reference point).
    cov_floor_m: std (m) added to both axes of every covariance; None = auto (half the
        median spacing of neighbouring reference points, at least 0.5 m).
    n_candidates: how many candidates a Fix lists.
    floor_classifier: a dedicated classifier picks the (building, floor) first and the
        model then only considers that floor's reference points (skipped when the site
        has one floor). "knn-svc" (default, chosen on UJIIndoorLoc's choosing users:
        benchmarks/floor_classifier_choice.py): `FloorKNN`'s building, then the SVC's
        floor among that building's; "svc": an RBF SVC over (building, floor) alone,
        fitted on a stratified sample of at most ``floor_classifier_rows`` fingerprints
        (default FLOOR_CLASSIFIER_ROWS); "trees": extra trees instead of the SVC;
        "knn": `FloorKNN` for both building and floor; None: the floor holding most of
        the model's own posterior mass wins.
    """

    name = "base"
    needs_fingerprints = True

    def __init__(
        self,
        *,
        kinds: Sequence[str] | None = None,
        use_heading: bool = False,
        missing: str = "floor",
        floor_dbm: float = -110.0,
        heading_weight: float | None = None,
        cov_floor_m: float | None = None,
        n_candidates: int = 5,
        floor_classifier: str | None = "knn-svc",
        floor_classifier_rows: int = FLOOR_CLASSIFIER_ROWS,
    ):
        self.kinds = None if kinds is None else list(kinds)
        self.use_heading = bool(use_heading)
        self.missing = missing
        self.floor_dbm = float(floor_dbm)
        self.heading_weight = heading_weight
        self.cov_floor_m = cov_floor_m
        self.n_candidates = int(n_candidates)
        if floor_classifier not in FLOOR_CLASSIFIERS:
            raise ValueError(f"floor_classifier must be one of {FLOOR_CLASSIFIERS}, not {floor_classifier!r}")
        self.floor_classifier = floor_classifier
        if int(floor_classifier_rows) < 1:
            raise ValueError("floor_classifier_rows must be at least 1")
        self.floor_classifier_rows = int(floor_classifier_rows)
        RssEncoder(missing, floor_dbm)  # validate early

    # ---- parameters --------------------------------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        names = []
        for klass in cls.__mro__:
            if "__init__" not in vars(klass) or klass is object:
                continue
            for p in inspect.signature(vars(klass)["__init__"]).parameters.values():
                if p.name != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL) and p.name not in names:
                    names.append(p.name)
        return names

    def get_params(self) -> dict:
        return {n: getattr(self, n) for n in self._param_names()}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    # ---- fitting -----------------------------------------------------------------
    def fit(self, fs: FingerprintSet) -> Self:
        t0 = time.perf_counter()
        fs = fs.select_kinds(self.kinds).drop_empty()
        if len(fs) == 0 and self.needs_fingerprints:
            raise ValueError("no fingerprint hears any transmitter of the selected kinds")
        self.tx_ids_ = list(fs.tx_ids)
        self.tx_index_ = {t: j for j, t in enumerate(self.tx_ids_)}
        self.encoder_ = RssEncoder(self.missing, self.floor_dbm)
        rp = fs.reference_points()
        self.rp_ = rp
        gkeys = sorted({(int(b), int(f)) for b, f in zip(rp.building, rp.floor, strict=True)})
        gindex = {k: i for i, k in enumerate(gkeys)}
        self.group_building_ = np.array([k[0] for k in gkeys], dtype=int)
        self.group_floor_ = np.array([k[1] for k in gkeys], dtype=int)
        self.rp_group_ = np.array([gindex[(int(b), int(f))] for b, f in zip(rp.building, rp.floor, strict=True)], dtype=int)
        self.rp_xy_ = rp.xy
        self.rp_key_index_ = {k: i for i, k in enumerate(rp.keys)}
        X = self.encoder_.transform(fs.rss)
        H = heading_features(fs.heading_deg) if self.use_heading else None
        self.cov_floor_m_ = self.cov_floor_m if self.cov_floor_m is not None else self._auto_cov_floor()
        if self.use_heading:
            self.heading_weight_ = (
                float(self.heading_weight) if self.heading_weight is not None
                else self._auto_heading_weight(X, rp.row_rp)
            )
        else:
            self.heading_weight_ = 0.0
        self.n_fingerprints_ = len(fs)
        data = TrainingData(fs=fs, rp=rp, row_group=self.rp_group_[rp.row_rp] if len(fs) else np.zeros(0, int))
        self.calibration_: CovarianceCalibration = IDENTITY  # the training step (or ``_fit``) calibrates
        #: the share of the fingerprints whose positions are crowd estimates, not surveyed (the training
        #: step knows; such a model is never restricted to ``near``, ``_near_mask``)
        self.crowd_share_ = 0.0
        self._fit(X, H, data)
        t1 = time.perf_counter()
        self.floor_clf_ = self._fit_floor_classifier(X, H, data)
        self.floor_fit_time_s_ = time.perf_counter() - t1
        self.fit_time_s_ = time.perf_counter() - t0
        return self

    def _fit(self, X: np.ndarray, H: np.ndarray | None, data: TrainingData) -> None:
        raise NotImplementedError

    def reuse_choices(self, validated: FingerprintModel) -> None:
        """Before fitting on all data: take what ``validated`` (the same model fitted on the
        validation split) chose by its own cross-validation, instead of choosing again —
        so the training step's second fit is cheap. Default: nothing to reuse."""

    def _floor_design(self, X, H):
        return X if H is None else np.hstack([X, self.heading_weight_ * H])

    def _fit_floor_classifier(self, X, H, data: TrainingData):
        """The (building, floor) classifier (``floor_classifier``). An SVC or extra trees
        is fitted on at most ``floor_classifier_rows`` fingerprints (a stratified sample:
        an RBF SVC's fit grows ≈ n², its size with n); `FloorKNN` on every row (O(n))."""
        row_group = data.row_group
        if self.floor_classifier is None or len(np.unique(row_group)) < 2:
            return None
        clf = None
        if self.floor_classifier != "knn":
            rows = stratified_rows(row_group, self.floor_classifier_rows)
            sample, labels = self._floor_design(X[rows], None if H is None else H[rows]), row_group[rows]
            if self.floor_classifier == "trees":
                from sklearn.ensemble import ExtraTreesClassifier

                return ExtraTreesClassifier(n_estimators=100, min_samples_leaf=1, random_state=0).fit(sample, labels)
            from sklearn.svm import SVC

            clf = SVC(C=10.0, gamma="scale").fit(sample, labels)
            if self.floor_classifier == "svc":
                return clf
        return FloorKNN(self.encoder_, X.shape[1]).fit(X, data.rp.row_rp, self.rp_group_, self.group_building_, svc=clf)

    def _auto_cov_floor(self) -> float:
        spacings = []
        for g in range(len(self.group_floor_)):
            xy = self.rp_xy_[self.rp_group_ == g]
            if len(xy) < 2:
                continue
            d = np.sqrt(((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1)) if len(xy) <= 2000 else None
            if d is None:
                continue
            np.fill_diagonal(d, np.inf)
            spacings.append(d.min(axis=1))
        if not spacings:
            return 1.0
        return max(0.5, 0.5 * float(np.median(np.concatenate(spacings))))

    def _auto_heading_weight(self, X: np.ndarray, row_rp: np.ndarray) -> float:
        """Half the typical distance, in the model's own distance, between a fingerprint and
        the mean of its reference point's (points with one fingerprint do not count)."""
        n_rp = row_rp.max() + 1 if len(row_rp) else 0
        if n_rp == 0:
            return 0.0
        counts = np.bincount(row_rp, minlength=n_rp)
        mean = np.zeros((n_rp, X.shape[1]))
        np.add.at(mean, row_rp, X)
        mean /= np.maximum(counts, 1)[:, None]
        own = counts[row_rp] > 1
        typical = self._typical_distance(X[own], mean[row_rp[own]]) if own.any() else 0.1
        return 0.5 * max(typical, 1e-3)

    def _typical_distance(self, X: np.ndarray, M: np.ndarray) -> float:
        """The median distance between the rows of ``X`` and ``M``: Euclidean here; a model
        searching with another distance overrides it."""
        return float(np.sqrt(np.median(((X - M) ** 2).sum(axis=1))))

    def _check_fitted(self) -> None:
        if not hasattr(self, "tx_ids_"):
            raise NotFittedError(f"{type(self).__name__} is not fitted")

    # ---- queries -----------------------------------------------------------------
    def scan_matrix(self, scans: Sequence[Mapping[str, float]]) -> np.ndarray:
        """Scans as ``{tx_id: dBm}`` dicts → (n, m) matrix in this model's column order.
        Transmitters unknown to the model (or of other kinds) are ignored."""
        self._check_fitted()
        R = np.full((len(scans), len(self.tx_ids_)), np.nan)
        idx = self.tx_index_
        for i, s in enumerate(scans):
            for tx, v in s.items():
                j = idx.get(tx)
                if j is not None and v is not None:
                    R[i, j] = float(v)
        return R

    def known_transmitters(self, rss: Mapping[str, float]) -> list[str]:
        self._check_fitted()
        return [t for t in rss if t in self.tx_index_]

    def _as_matrix(self, rss) -> np.ndarray:
        if isinstance(rss, np.ndarray):
            R = np.atleast_2d(np.asarray(rss, dtype=float))
            if R.shape[1] != len(self.tx_ids_):
                raise ValueError(f"RSS matrix has {R.shape[1]} columns, model has {len(self.tx_ids_)} transmitters")
            return R
        if isinstance(rss, FingerprintSet):
            return rss.aligned_rss(self.tx_ids_)
        return self.scan_matrix(list(rss))

    def _headings(self, heading_deg, n: int) -> np.ndarray | None:
        if not self.use_heading:
            return None
        if heading_deg is None:
            return np.zeros((n, 2), dtype=np.float32)
        h = np.atleast_1d(np.asarray([np.nan if v is None else v for v in np.atleast_1d(heading_deg)], dtype=float))
        if len(h) == 1 and n != 1:
            h = np.repeat(h, n)
        return heading_features(h)

    def _near_mask(self, near, radius_m, n: int) -> np.ndarray | None:
        """Which reference points each query may answer with (None: any). A model trained on crowd
        fingerprints is not restricted: its positions are where earlier tracking sessions believed they
        were, and a map of those restricted to where a session believes it is confirms the error they
        share instead of measuring it (docs/tracking-design.md, "A defect the circle brought"; an
        artifact stored before ``crowd_share_`` counts as survey-only until retrained)."""
        a = _near_array(near, n)
        if a is None or radius_m is None or getattr(self, "crowd_share_", 0.0) > 0:
            return None
        d2 = ((self.rp_xy_[None, :, :] - a[:, None, :2]) ** 2).sum(-1)
        mask = d2 <= float(radius_m) ** 2
        has_floor = ~np.isnan(a[:, 2])
        if has_floor.any():
            rp_floor = self.group_floor_[self.rp_group_]
            mask[has_floor] &= rp_floor[None, :] == a[has_floor, 2][:, None]
        mask[~mask.any(axis=1)] = True  # nothing near: no restriction for that query
        return mask

    def predict(self, rss, heading_deg=None, *, near=None, radius_m: float | None = None,
                chunk: int = 256, calibrated: bool = True) -> Prediction:
        """Vectorised estimate for many scans.

        rss: (n, m) matrix in ``tx_ids_`` order (NaN = not heard), a FingerprintSet, or
        a list of ``{tx_id: dBm}``. heading_deg: None, a scalar or (n,) (NaN/None =
        unknown). near/radius_m: restrict to reference points within ``radius_m`` of
        ``near`` = (x, y[, floor]) or a previous Fix (spatial filtering when tracking).
        calibrated: covariances through ``calibration_`` (False: the model's raw ones,
        which the calibration is fitted on).
        """
        pred = self._predict(rss, heading_deg, near=near, radius_m=radius_m, chunk=chunk)
        cal = getattr(self, "calibration_", IDENTITY)
        if calibrated and cal != IDENTITY:
            pred.covariance = cal.apply(pred.covariance)
        return pred

    def _predict(self, rss, heading_deg, *, near, radius_m, chunk: int) -> Prediction:
        """`predict` with the model's raw covariance."""
        self._check_fitted()
        R = self._as_matrix(rss)
        n = R.shape[0]
        Q = self.encoder_.transform(R)
        Hq = self._headings(heading_deg, n)
        mask = self._near_mask(near, radius_m, n)
        clf = getattr(self, "floor_clf_", None)
        if clf is not None and n:
            g = clf.predict(self._floor_design(Q, Hq))
            on_floor = self.rp_group_[None, :] == g[:, None]
            mask = on_floor if mask is None else np.where((mask & on_floor).any(1)[:, None], mask & on_floor, on_floor)
        parts = []
        for s in range(0, n, chunk):
            sl = slice(s, s + chunk)
            m = None if mask is None else mask[sl]
            logs = self._log_scores(Q[sl], None if Hq is None else Hq[sl], m)
            if m is not None:
                logs = restricted(logs, m)
            parts.append(self._reduce(logs))
        return _concat_predictions(parts)

    def _reduce(self, logs: np.ndarray) -> Prediction:
        return reduce_live(
            logs, self.rp_xy_, self.rp_group_, self.group_floor_, self.group_building_,
            self.cov_floor_m_, self.n_candidates,
        )

    def _log_scores(self, Q: np.ndarray, Hq: np.ndarray | None, mask: np.ndarray | None) -> np.ndarray:
        raise NotImplementedError

    def fixes(self, pred: Prediction) -> list[Fix]:
        """One Fix per query: the (building, floor) the posterior chose, and candidates of that floor."""
        labels = self.rp_.labels
        share = getattr(self, "calibration_", IDENTITY).walk_share
        out = []
        for i in range(len(pred)):
            cands = [
                Candidate(label=labels[r], x=float(self.rp_xy_[r, 0]), y=float(self.rp_xy_[r, 1]),
                          floor=int(self.rp_.floor[r]), probability=float(p), building=int(self.rp_.building[r]))
                for r, p in zip(pred.top_rp[i], pred.top_p[i], strict=True) if p > 0 and r >= 0
            ]
            best = int(pred.best_rp[i])
            out.append(Fix(
                x=float(pred.x[i]), y=float(pred.y[i]), floor=int(pred.floor[i]),
                covariance=pred.covariance[i].copy(),
                reference_point=labels[best] if best >= 0 else None,
                candidates=cands, building=int(pred.building[i]), shared_share=share,
            ))
        return out

    def locate(self, rss: Mapping[str, float], heading_deg: float | None = None, *,
               near=None, radius_m: float | None = None) -> Fix:
        """One scan ``{tx_id: dBm}`` → Fix. Raises UnknownTransmittersError when no
        transmitter of the scan is known to the model."""
        self._check_fitted()
        if not self.known_transmitters(rss):
            raise UnknownTransmittersError("no transmitter in the scan is known to the model")
        pred = self.predict(self.scan_matrix([rss]), heading_deg, near=near, radius_m=radius_m)
        return self.fixes(pred)[0]

    def locate_many(self, rss, heading_deg=None, *, near=None, radius_m: float | None = None) -> list[Fix]:
        """Many scans (list of dicts, matrix or FingerprintSet) → list of Fix."""
        return self.fixes(self.predict(rss, heading_deg, near=near, radius_m=radius_m))


def _concat_predictions(parts: list[Prediction]) -> Prediction:
    if len(parts) == 1:
        return parts[0]
    if not parts:
        z = np.zeros(0)
        return Prediction(z, z, z.astype(int), z.astype(int), np.zeros((0, 2, 2)), z.astype(int),
                          np.zeros((0, 0), int), np.zeros((0, 0)))
    cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
    return Prediction(cat("x"), cat("y"), cat("floor"), cat("building"), cat("covariance"),
                      cat("best_rp"), cat("top_rp"), cat("top_p"))
