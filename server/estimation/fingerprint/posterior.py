"""From log-scores over reference points to a fix: floor first, then position.

Every model produces, per query, log-scores over the reference points (RPs) it was
trained on (−inf = impossible). `reduce_posterior`:

1. turns them into a posterior, sums it per (building, floor) group and picks the
   group with the most mass (the floor "vote");
2. keeps only the RPs of that group and renormalises — the position can never come
   from another floor;
3. reduces that mixture of RPs to its first two moments (mean, 2×2 covariance) and
   adds ``cov_floor_m² · I`` so the covariance is usable as a tracker's R even when
   the posterior is a single RP;
4. reports the best RP and the top candidates (probabilities within the floor).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def softmax_rows(logs: np.ndarray) -> np.ndarray:
    m = np.max(logs, axis=1, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    p = np.exp(logs - m)
    s = p.sum(axis=1, keepdims=True)
    return np.divide(p, s, out=np.zeros_like(p), where=s > 0)


@dataclass
class Prediction:
    """Vectorised answer for n queries (arrays, no Python objects per query)."""

    x: np.ndarray
    y: np.ndarray
    floor: np.ndarray
    building: np.ndarray
    covariance: np.ndarray  # (n, 2, 2)
    best_rp: np.ndarray  # (n,) RP index
    top_rp: np.ndarray  # (n, c) RP indices, best first
    top_p: np.ndarray  # (n, c) probabilities

    def __len__(self) -> int:
        return len(self.x)

    @property
    def xy(self) -> np.ndarray:
        return np.column_stack([self.x, self.y])


def reduce_posterior(
    logs: np.ndarray,
    rp_xy: np.ndarray,
    rp_group: np.ndarray,
    group_floor: np.ndarray,
    group_building: np.ndarray,
    cov_floor_m: float,
    n_candidates: int = 5,
) -> Prediction:
    n, n_rp = logs.shape
    n_groups = len(group_floor)
    P = softmax_rows(logs)
    mass = np.zeros((n, n_groups))
    for g in range(n_groups):  # groups are few (floors × buildings)
        mass[:, g] = P[:, rp_group == g].sum(axis=1)
    g_best = np.argmax(mass, axis=1)
    on_floor = rp_group[None, :] == g_best[:, None]
    P = np.where(on_floor, P, 0.0)
    s = P.sum(axis=1, keepdims=True)
    empty = s[:, 0] <= 0
    if empty.any():  # no mass on the chosen group: uniform over its RPs
        P[empty] = on_floor[empty].astype(float)
        s = P.sum(axis=1, keepdims=True)
    P /= s
    mean = P @ rp_xy
    d = rp_xy[None, :, :] - mean[:, None, :]
    cov = np.einsum("nr,nri,nrj->nij", P, d, d)
    cov[:, 0, 0] += cov_floor_m**2
    cov[:, 1, 1] += cov_floor_m**2
    c = min(n_candidates, n_rp)
    top = np.argpartition(-P, c - 1, axis=1)[:, :c] if c < n_rp else np.tile(np.arange(n_rp), (n, 1))
    top_p = np.take_along_axis(P, top, axis=1)
    order = np.argsort(-top_p, axis=1, kind="stable")
    top = np.take_along_axis(top, order, axis=1)
    top_p = np.take_along_axis(top_p, order, axis=1)
    return Prediction(
        x=mean[:, 0], y=mean[:, 1],
        floor=group_floor[g_best], building=group_building[g_best],
        covariance=cov, best_rp=top[:, 0], top_rp=top, top_p=top_p,
    )


def reduce_live(
    logs: np.ndarray,
    rp_xy: np.ndarray,
    rp_group: np.ndarray,
    group_floor: np.ndarray,
    group_building: np.ndarray,
    cov_floor_m: float,
    n_candidates: int = 5,
) -> Prediction:
    """``reduce_posterior`` over only the reference points some query gives weight to (a
    k-NN's posterior has k of thousands) and their (building, floor) groups (the group with
    the most mass is one of them), indices mapped back (``columns_back``). The same answer
    as over every column: a reference point of log-score −inf has probability 0. When some
    query gives weight to none (then its floor is the first group's, uniform over its
    points), or to every column, it is the plain reduction. One query (a session's fix, a
    ``locate``) takes ``_reduce_one``."""
    live = np.isfinite(logs)
    if len(logs) == 1 and live.any():
        return _reduce_one(logs[0], np.flatnonzero(live[0]), rp_xy, rp_group, group_floor, group_building,
                           cov_floor_m, n_candidates)
    cols = np.flatnonzero(live.any(axis=0))
    if len(cols) in (0, logs.shape[1]) or not live.any(axis=1).all():
        return reduce_posterior(logs, rp_xy, rp_group, group_floor, group_building, cov_floor_m, n_candidates)
    groups, sub_group = unique_inverse(rp_group[cols])
    pred = reduce_posterior(logs[:, cols], rp_xy[cols], sub_group, group_floor[groups], group_building[groups],
                            cov_floor_m, n_candidates)
    return columns_back(pred, cols, logs.shape[1], n_candidates)


def _reduce_one(logs: np.ndarray, cols: np.ndarray, rp_xy: np.ndarray, rp_group: np.ndarray,
                group_floor: np.ndarray, group_building: np.ndarray, cov_floor_m: float,
                n_candidates: int) -> Prediction:
    """``reduce_posterior`` of one query over its live columns ``cols``, written out for the
    few values a session's fix has (a dozen NumPy calls on (n_rp,) arrays cost more than the
    arithmetic): the same floor, moments and candidates."""
    p = np.exp(logs[cols] - logs[cols].max())
    groups = rp_group[cols]
    best = int(np.argmax(np.bincount(groups, weights=p)))  # ties: the lowest group
    keep = groups == best
    cols, p = cols[keep], p[keep] / p[keep].sum()
    xy = rp_xy[cols]
    mean = p @ xy
    d = xy - mean
    cov = (d * p[:, None]).T @ d + cov_floor_m**2 * np.eye(2)
    c = min(n_candidates, len(rp_xy))
    order = np.argsort(-p, kind="stable")[:c]
    top = np.full(c, -1)
    top_p = np.zeros(c)
    top[: len(order)], top_p[: len(order)] = cols[order], p[order]
    return Prediction(
        x=mean[:1].copy(), y=mean[1:].copy(), floor=group_floor[[best]], building=group_building[[best]],
        covariance=cov[None], best_rp=top[:1].copy(), top_rp=top[None], top_p=top_p[None],
    )


def unique_inverse(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)`` for a short 1-D integer array (a query's few
    reference points' groups), without its sort machinery."""
    distinct = sorted(set(values.tolist()))
    index = {v: i for i, v in enumerate(distinct)}
    return np.array(distinct, dtype=values.dtype), np.array([index[v] for v in values.tolist()], dtype=np.intp)


def columns_back(pred: Prediction, cols: np.ndarray, n_rp: int, n_candidates: int) -> Prediction:
    """``pred``, reduced over the reference points ``cols`` only (of ``n_rp``), with its indices
    mapped back to all of them: candidates without probability become −1 and the list is
    padded with (−1, 0) to min(``n_candidates``, ``n_rp``)."""
    pred.best_rp = cols[pred.best_rp]
    top = np.where(pred.top_p > 0, cols[pred.top_rp], -1)
    pad = min(n_candidates, n_rp) - top.shape[1]
    if pad > 0:
        top = np.concatenate([top, np.full((len(top), pad), -1)], axis=1)
        pred.top_p = np.concatenate([pred.top_p, np.zeros((len(top), pad))], axis=1)
    pred.top_rp = top
    return pred
