"""Propagation (path-loss) model: for sites with transmitter positions and few or no
fingerprints.

Log-distance path loss (``server.estimation.radio``; d ≥ 1 m). Per transmitter, R0 and γ are

- taken from the site's Transmitter records (``tx_power_dbm``, ``path_loss_exponent``)
  when given, else
- fitted by least squares on the survey fingerprints that heard it (distance from the
  transmitter's known position, or from a position estimated as the power-weighted
  centroid of its strongest readings), else
- a pooled fit over all transmitters, else the defaults.

Locating one scan: floor = the (building, floor) classifier's answer when the model
was fitted on fingerprints of several floors (``floor_classifier``, as for every
model), else a power-weighted vote of the strongest heard transmitters' floors; ranges
from the inverted path loss (horizontal, after removing the floor height difference);
then least-squares multilateration (relative range residuals, soft-L1 loss) or the
weighted path-loss centroid (weights 1/d). With fingerprints the
estimate is turned into a posterior over the reference points of that floor like every
other model; without, the fix is the estimate with its least-squares covariance.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from server.estimation.radio import fit_path_loss, multilaterate, range_from_rss, weighted_centroid
from server.estimation.types import Fix

from .base import FingerprintModel, TrainingData, _concat_predictions, restricted
from .dataset import FingerprintSet, tx_kind
from .posterior import Prediction

METHODS = ("multilateration", "centroid")


# ---- the model --------------------------------------------------------------------------
class PropagationModel(FingerprintModel):
    """transmitters: API Transmitter dicts ``{id, floor?, x?, y?, tx_power_dbm?,
    path_loss_exponent?}`` (``building?`` accepted too). method: "multilateration" or
    "centroid". floor_height_m: vertical distance per floor. max_anchors: strongest
    transmitters used per scan. ``near``/``radius_m`` (a tracking session's search circle) restrict
    the reference points a fix is reduced to; a model without reference points answers the
    multilateration unrestricted."""

    name = "propagation"
    needs_fingerprints = False

    def __init__(self, transmitters: Sequence[Mapping] | None = None, method: str = "multilateration",
                 floor_height_m: float = 4.0, default_r0: float = -45.0, default_gamma: float = 2.5,
                 max_anchors: int = 8, **common):
        super().__init__(**common)
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}")
        self.transmitters = None if transmitters is None else [dict(t) for t in transmitters]
        self.method = method
        self.floor_height_m = float(floor_height_m)
        self.default_r0 = float(default_r0)
        self.default_gamma = float(default_gamma)
        self.max_anchors = int(max_anchors)

    def fit(self, fs: FingerprintSet | None = None) -> PropagationModel:
        known = [t for t in (self.transmitters or []) if not self.kinds or tx_kind(t["id"]) in self.kinds]
        if fs is None:
            fs = FingerprintSet(rss=np.zeros((0, len(known))), tx_ids=[t["id"] for t in known],
                                x=np.zeros(0), y=np.zeros(0), floor=np.zeros(0, dtype=int))
        missing_cols = [t["id"] for t in known if t["id"] not in fs.tx_ids]
        if missing_cols:
            fs = fs.select_transmitters(list(fs.tx_ids) + missing_cols)
        return super().fit(fs)

    def _fit(self, X, H, data: TrainingData) -> None:
        fs = data.fs
        m = len(self.tx_ids_)
        info = {t["id"]: t for t in (self.transmitters or [])}
        pos = np.full((m, 2), np.nan)
        floor = np.zeros(m, dtype=int)
        building = np.zeros(m, dtype=int)
        r0 = np.full(m, np.nan)
        gamma = np.full(m, np.nan)
        for j, tx in enumerate(self.tx_ids_):
            t = info.get(tx, {})
            if t.get("x") is not None and t.get("y") is not None:
                pos[j] = (float(t["x"]), float(t["y"]))
                floor[j] = int(t.get("floor") or 0)
                building[j] = int(t.get("building") or 0)
            elif len(fs):
                heard = np.flatnonzero(~np.isnan(fs.rss[:, j]))
                if len(heard):
                    top = heard[np.argsort(-fs.rss[heard, j])[:5]]
                    w = 10.0 ** (fs.rss[top, j] / 10.0)
                    pos[j] = (np.sum(w * fs.x[top]) / w.sum(), np.sum(w * fs.y[top]) / w.sum())
                    floor[j] = int(fs.floor[top[0]])
                    building[j] = int(fs.building[top[0]])
            if t.get("tx_power_dbm") is not None:
                r0[j] = float(t["tx_power_dbm"])
            if t.get("path_loss_exponent") is not None:
                gamma[j] = float(t["path_loss_exponent"])
        # least-squares R0, γ from the survey where not given
        all_d, all_r = [], []
        fitted = np.zeros(m, dtype=bool)
        fr0, fg = np.full(m, np.nan), np.full(m, np.nan)
        for j in range(m):
            if len(fs) == 0 or np.isnan(pos[j, 0]):
                continue
            heard = ~np.isnan(fs.rss[:, j]) & (fs.building == building[j])
            if heard.sum() < 3:
                continue
            d = self._distance(pos[j], floor[j], fs.x[heard], fs.y[heard], fs.floor[heard])
            all_d.append(d)
            all_r.append(fs.rss[heard, j])
            try:
                fr0[j], fg[j] = fit_path_loss(d, fs.rss[heard, j])
                fitted[j] = True
            except ValueError:
                pass
        pooled = (self.default_r0, self.default_gamma)
        if all_d:
            try:
                pooled = fit_path_loss(np.concatenate(all_d), np.concatenate(all_r))
            except ValueError:
                pass
        self.pooled_params_ = pooled
        r0 = np.where(np.isnan(r0), np.where(fitted, fr0, pooled[0]), r0)
        gamma = np.where(np.isnan(gamma), np.where(fitted, fg, pooled[1]), gamma)
        self.tx_pos_, self.tx_floor_, self.tx_building_ = pos, floor, building
        self.r0_, self.gamma_ = r0, gamma

    def _distance(self, p, floor, x, y, floors):
        dz = (np.asarray(floors) - floor) * self.floor_height_m
        return np.sqrt((np.asarray(x) - p[0]) ** 2 + (np.asarray(y) - p[1]) ** 2 + dz**2)

    def transmitter_params(self) -> list[dict]:
        """Positions and fitted radio parameters, as API Transmitter dicts."""
        self._check_fitted()
        return [
            {"id": t, "kind": tx_kind(t), "floor": int(self.tx_floor_[j]), "building": int(self.tx_building_[j]),
             "x": None if np.isnan(self.tx_pos_[j, 0]) else float(self.tx_pos_[j, 0]),
             "y": None if np.isnan(self.tx_pos_[j, 1]) else float(self.tx_pos_[j, 1]),
             "tx_power_dbm": float(self.r0_[j]), "path_loss_exponent": float(self.gamma_[j])}
            for j, t in enumerate(self.tx_ids_)
        ]

    def known_transmitters(self, rss):
        self._check_fitted()
        return [t for t in rss if t in self.tx_index_ and not np.isnan(self.tx_pos_[self.tx_index_[t], 0])]

    def estimate(self, rss_row: np.ndarray, group: tuple[int, int] | None = None):
        """One (m,) RSS row → (xy, cov, building, floor) or None when no anchor is heard.
        ``group`` = (building, floor) imposes the floor instead of the transmitter vote."""
        ok = np.flatnonzero(~np.isnan(rss_row) & ~np.isnan(self.tx_pos_[:, 0]))
        if len(ok) == 0:
            return None
        ok = ok[np.argsort(-rss_row[ok])][: self.max_anchors]
        power = 10.0 ** (rss_row[ok] / 10.0)
        votes: dict[tuple, float] = {}
        for j, w in zip(ok[:3], power[:3], strict=True):
            key = (int(self.tx_building_[j]), int(self.tx_floor_[j]))
            votes[key] = votes.get(key, 0.0) + w
        building, floor = max(votes, key=lambda k: votes[k]) if group is None else group
        d = range_from_rss(rss_row[ok], self.r0_[ok], self.gamma_[ok])
        dz = (self.tx_floor_[ok] - floor) * self.floor_height_m
        r = np.sqrt(np.maximum(d**2 - dz**2, 0.25))
        A = self.tx_pos_[ok]
        if self.method == "centroid":
            xy = weighted_centroid(A, r)
            w = 1.0 / np.maximum(r, 0.1)
            w /= w.sum()
            dev = A - xy
            cov = (w[:, None, None] * np.einsum("ni,nj->nij", dev, dev)).sum(0) + np.eye(2) * float(np.min(r)) ** 2 / 4
        else:
            xy, cov = multilaterate(A, r)
        return xy, cov, building, floor

    def _predict(self, rss, heading_deg, *, near, radius_m, chunk: int) -> Prediction:
        self._check_fitted()
        R = self._as_matrix(rss)
        n = len(R)
        clf = getattr(self, "floor_clf_", None)
        groups: list[tuple[int, int] | None] = [None] * n
        if clf is not None and n:
            g = clf.predict(self._floor_design(self.encoder_.transform(R), self._headings(heading_deg, n)))
            groups = [(int(self.group_building_[k]), int(self.group_floor_[k])) for k in g]
        est = [self.estimate(R[i], groups[i]) for i in range(n)]
        near_mask = self._near_mask(near, radius_m, n)  # (a tracking session's search circle)
        parts = []
        for i, e in enumerate(est):
            if e is None:  # nothing usable heard: centre of everything known, huge covariance
                known = self.tx_pos_[~np.isnan(self.tx_pos_[:, 0])]
                c = known.mean(0) if len(known) else np.zeros(2)
                e = (c, np.eye(2) * 1e4, 0, 0)
            xy, cov, b, f = e
            g = np.flatnonzero((self.group_building_ == b) & (self.group_floor_ == f))
            if len(self.rp_xy_) and len(g):
                sigma2 = max(float(np.trace(cov)) / 2.0, self.cov_floor_m_**2)
                logs = -((self.rp_xy_ - xy) ** 2).sum(-1) / (2.0 * sigma2)
                logs = np.where(self.rp_group_ == g[0], logs, -np.inf)[None, :]
                if near_mask is not None:  # the circle's points, unless it holds none of the floor's
                    logs = restricted(logs, near_mask[i : i + 1])
                parts.append(self._reduce(logs))
            else:
                cov = cov + np.eye(2) * self.cov_floor_m_**2
                c = min(self.n_candidates, len(self.rp_xy_)) or self.n_candidates
                parts.append(Prediction(
                    x=np.array([xy[0]]), y=np.array([xy[1]]), floor=np.array([f]), building=np.array([b]),
                    covariance=cov[None], best_rp=np.array([-1]), top_rp=np.full((1, c), -1), top_p=np.zeros((1, c)),
                ))
        return _concat_predictions(parts)

    def fixes(self, pred: Prediction) -> list[Fix]:
        if len(self.rp_xy_):
            return super().fixes(pred)
        return [Fix(x=float(pred.x[i]), y=float(pred.y[i]), floor=int(pred.floor[i]),
                    covariance=pred.covariance[i].copy(), building=int(pred.building[i])) for i in range(len(pred))]
