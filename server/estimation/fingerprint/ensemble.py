"""An ensemble of fingerprint models ("ensemble"): a floor vote, then the members' mean position.

Each member is an existing model (``make_model(algorithm, params)``), fitted on the same
fingerprints; a query is answered by every member and the answers are combined:

1. **(building, floor)**: the one most members answer; a tie goes to the earliest member
   (in ``members`` order) among the tied answers.
2. **Position**: the mean (``position="mean"``) or the coordinate-wise median
   (``"median"``) of the positions of the members that answered that (building, floor) —
   a member that put the scan on another floor does not pull the position.
3. **Covariance**: the moments of an equal mixture of those members' Gaussians about the
   combined position: ``mean_i(C_i) + mean_i((x_i − x)(x_i − x)ᵀ)`` (each ``C_i`` the
   member's own, calibrated, covariance); the training step then calibrates the
   ensemble's covariance like any model's (``calibration_``).
4. **Candidates**: the reference points of those members' candidate lists, each with the
   mean of its probability over them (0 where a member does not list it), best first.

The default members are the combination chosen on UJIIndoorLoc's choosing users
(benchmarks/fingerprint_ensemble.py): wknn over the positive ("floor") representation,
wknn over the powed one (both Sørensen), and knn with its default floor classifier —
9.43 m mean against wknn's 9.88 m there, floor hit 59.1 % against 59.0 %. Measured once
on the reporting users it lost (12.21 m against wknn's 11.96 m, floor 75.0 % against
75.5 %), so it is selectable, not the default.

Fitting costs the members' fits added up (each does its own cross-validation), a query
the members' queries. ``reuse_choices`` passes each validated member's choices (and its
calibration) to the member it becomes, so the training step's second fit is as cheap
as each member's.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any, Self

import numpy as np

from .base import FingerprintModel
from .calibration import IDENTITY
from .dataset import FingerprintSet
from .posterior import Prediction

POSITIONS = ("mean", "median")
#: chosen on UJIIndoorLoc's choosing users (module docstring)
DEFAULT_MEMBERS: tuple[dict, ...] = (
    {"algorithm": "wknn", "params": {"missing": "floor"}},
    {"algorithm": "wknn", "params": {"missing": "powed"}},
    {"algorithm": "knn", "params": {}},
)
#: set on the ensemble, for every member alike (not in a member's params)
_SHARED = ("kinds", "use_heading")


def _member_spec(spec: Any) -> dict:
    if not isinstance(spec, Mapping) or not isinstance(spec.get("algorithm"), str):
        raise ValueError(f"an ensemble member is {{'algorithm': name, 'params': {{...}}}}, not {spec!r}")
    extra = set(spec) - {"algorithm", "params"}
    if extra:
        raise ValueError(f"unknown keys in an ensemble member: {sorted(extra)}")
    params = spec.get("params") or {}
    if not isinstance(params, Mapping):
        raise ValueError("an ensemble member's params must be a mapping")
    if spec["algorithm"] == "ensemble":
        raise ValueError("an ensemble member cannot be an ensemble")
    shared = set(params) & set(_SHARED)
    if shared:
        raise ValueError(f"{sorted(shared)} are set on the ensemble, not on a member")
    return {"algorithm": spec["algorithm"], "params": dict(params)}


def vote_groups(answers: np.ndarray) -> np.ndarray:
    """(n,) per row of ``answers`` (n, members), the value most members give; on a tie the
    earliest member's among the tied values."""
    answers = np.asarray(answers)
    n, m = answers.shape
    counts = (answers[:, :, None] == answers[:, None, :]).sum(axis=2)  # (n, m): votes for member j's answer
    top = counts == counts.max(axis=1, keepdims=True)
    return answers[np.arange(n), np.argmax(top, axis=1)]


class EnsembleModel(FingerprintModel):
    """members: list of ``{"algorithm": name, "params": {...}}`` (default DEFAULT_MEMBERS; at
    least one, no nested ensembles; ``kinds``/``use_heading`` are the ensemble's and apply to
    every member); position: "mean" or "median" of the positions of the members on the voted
    (building, floor). The common ``floor_classifier`` belongs to the members (a member's
    params), not to the ensemble; the other common parameters except ``kinds``,
    ``use_heading`` and ``n_candidates`` are the members' own too."""

    name = "ensemble"

    def __init__(self, members: Sequence[Mapping] | None = None, position: str = "mean",
                 floor_classifier: str | None = None, **common):
        if floor_classifier is not None:
            raise ValueError("an ensemble has no floor_classifier of its own: set it in a member's params")
        super().__init__(floor_classifier=None, **common)
        specs = [_member_spec(s) for s in (DEFAULT_MEMBERS if members is None else members)]
        if not specs:
            raise ValueError("an ensemble needs at least one member")
        if position not in POSITIONS:
            raise ValueError(f"position must be one of {POSITIONS}")
        self.members = specs
        self.position = position
        for s in specs:  # unknown algorithms or parameters: ValueError now, not at fit
            self._make_member(s)

    def _make_member(self, spec: dict) -> FingerprintModel:
        from .registry import make_model  # the registry imports this module

        return make_model(spec["algorithm"], spec["params"], use_heading=self.use_heading)

    # ---- fit ---------------------------------------------------------------------------
    def reuse_choices(self, validated: FingerprintModel) -> None:
        """Each member takes the choices of the same member of ``validated`` (the ensemble
        fitted on the validation split) and, after its fit, that member's calibration."""
        if isinstance(validated, EnsembleModel) and len(getattr(validated, "members_", [])) == len(self.members):
            self._reused: list[FingerprintModel] | None = list(validated.members_)

    def fit(self, fs: FingerprintSet) -> Self:
        t0 = time.perf_counter()
        reused = self.__dict__.pop("_reused", None)  # never stored in the artifact
        fs = fs.select_kinds(self.kinds).drop_empty()
        if len(fs) == 0:
            raise ValueError("no fingerprint hears any transmitter of the selected kinds")
        self.tx_ids_ = list(fs.tx_ids)
        self.tx_index_ = {t: j for j, t in enumerate(self.tx_ids_)}
        rp = fs.reference_points()
        self.rp_ = rp
        gkeys = sorted({(int(b), int(f)) for b, f in zip(rp.building, rp.floor, strict=True)})
        self.group_building_ = np.array([k[0] for k in gkeys], dtype=int)
        self.group_floor_ = np.array([k[1] for k in gkeys], dtype=int)
        self.group_index_ = {k: i for i, k in enumerate(gkeys)}
        self.rp_group_ = np.array([self.group_index_[(int(b), int(f))]
                                   for b, f in zip(rp.building, rp.floor, strict=True)], dtype=int)
        self.rp_xy_ = rp.xy
        self.rp_key_index_ = {k: i for i, k in enumerate(rp.keys)}
        self.n_fingerprints_ = len(fs)
        self.heading_weight_ = 0.0
        self.calibration_ = IDENTITY  # the training step calibrates the combined covariance
        members: list[FingerprintModel] = []
        for i, spec in enumerate(self.members):
            m = self._make_member(spec)
            if reused is not None:
                m.reuse_choices(reused[i])
            m.fit(fs)
            if reused is not None:
                m.calibration_ = reused[i].calibration_
            members.append(m)
        self.members_ = members
        # each member's transmitters among the ensemble's columns, its reference points among the ensemble's
        self.member_cols_ = [np.array([self.tx_index_[t] for t in m.tx_ids_], dtype=np.int64) for m in members]
        self.member_rp_ = [np.array([self.rp_key_index_[k] for k in m.rp_.keys], dtype=np.int64) for m in members]
        # every covariance the ensemble answers is at least the smallest member's floor, after its calibration
        self.cov_floor_m_ = min(float(np.sqrt(m.calibration_.apply(np.eye(2)[None] * m.cov_floor_m_**2)[0, 0, 0]))
                                for m in members)
        self.fit_time_s_ = time.perf_counter() - t0
        self.floor_fit_time_s_ = 0.0
        return self

    # ---- queries -----------------------------------------------------------------------
    def _member_predictions(self, R: np.ndarray, heading_deg, near, radius_m, chunk) -> list[Prediction]:
        return [m.predict(R[:, cols], heading_deg, near=near, radius_m=radius_m, chunk=chunk)
                for m, cols in zip(self.members_, self.member_cols_, strict=True)]

    def _predict(self, rss, heading_deg, *, near, radius_m, chunk: int) -> Prediction:
        """The combination of the members' (calibrated) answers (module docstring)."""
        self._check_fitted()
        R = self._as_matrix(rss)
        n = R.shape[0]
        preds = self._member_predictions(R, heading_deg, near, radius_m, chunk)
        G = np.column_stack([np.array([self.group_index_[(int(b), int(f))] for b, f in
                                       zip(p.building, p.floor, strict=True)], dtype=np.int64).reshape(n)
                             for p in preds]) if n else np.zeros((0, len(preds)), dtype=np.int64)
        g = vote_groups(G) if n else np.zeros(0, dtype=np.int64)
        on = (G == g[:, None]).T  # (members, n): the members that answered the voted group
        XY = np.stack([p.xy for p in preds])  # (members, n, 2)
        w = on[..., None].astype(float)
        if self.position == "mean":
            xy = (XY * w).sum(axis=0) / w.sum(axis=0)
        else:
            xy = np.nanmedian(np.where(on[..., None], XY, np.nan), axis=0) if n else np.zeros((0, 2))
        d = XY - xy[None]
        C = np.stack([p.covariance for p in preds]) + d[..., :, None] * d[..., None, :]  # (members, n, 2, 2)
        cov = (C * w[..., None]).sum(axis=0) / w.sum(axis=0)[..., None]
        top_rp, top_p = self._candidates(preds, on, n)
        return Prediction(x=xy[:, 0], y=xy[:, 1], floor=self.group_floor_[g], building=self.group_building_[g],
                          covariance=cov, best_rp=top_rp[:, 0], top_rp=top_rp, top_p=top_p)

    def _candidates(self, preds: list[Prediction], on: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Per query, the reference points the members on the voted group list, each with the
        mean of its probability over those members, best first, padded with (−1, 0)."""
        c = min(self.n_candidates, len(self.rp_xy_))
        top_rp, top_p = np.full((n, c), -1, dtype=np.int64), np.zeros((n, c))
        for i in range(n):
            acc: dict[int, float] = {}
            voters = np.flatnonzero(on[:, i])
            for j in voters:
                p = preds[j]
                for r, q in zip(p.top_rp[i], p.top_p[i], strict=True):
                    if r >= 0 and q > 0:
                        key = int(self.member_rp_[j][r])
                        acc[key] = acc.get(key, 0.0) + float(q) / len(voters)
            best = sorted(acc.items(), key=lambda kv: (-kv[1], kv[0]))[:c]
            for k, (r, q) in enumerate(best):
                top_rp[i, k], top_p[i, k] = r, q
        return top_rp, top_p
