"""A fixed-interval (Rauch–Tung–Striebel) smoother over a stored track.

A session's track holds, in time order, one ``Estimate`` per input: a step's estimate is
the tracker's *prediction* for the new position (x⁻, P⁻ = P + Q), a scan's the *update*
at the same position. So the track alone carries what the RTS recursion needs for the
position: time index k advances at each step; the filtered state of k is its last
estimate, the predicted state of k + 1 the next step's estimate, and with the position
moving as x_{k+1} = x_k + u_k (F = I),

    C_k = P_{k|k} P_{k+1|k}⁻¹,
    x_{k|N} = x_{k|k} + C_k (x_{k+1|N} − x_{k+1|k}),
    P_{k|N} = P_{k|k} + C_k (P_{k+1|N} − P_{k+1|k}) C_kᵀ.

This is the exact RTS smoother of the two-state Kalman filters (``kf``, ``fkf``,
``ekf-xy``, whose position Jacobian is I) and, for the self-calibrating and sample-based
filters, the smoother of their position marginal (the coupling through the heading bias is
left out). Every estimate of index k gets the smoothed state of k; a floor change starts a
new interval. Nothing here needs the tracker: it runs on what the server stores.

So it needs neither the filter's kind nor the steps and fixes themselves: the process noise
of step k is read off the stored covariances, Q_k = P_{k+1|k} − P_{k|k} (the growth from the
filtered estimate to the next step's prediction, its negative part dropped: a PF's cloud may
shrink in a step where walls kill particles, ``_predicted_cov``), and each fix enters through the scan
estimate it produced (a refused fix moved nothing there, so it moves nothing here either).
``GET /api/v1/sessions/{id}/track?smoothed=true`` serves it.

Where the floor has a walkable area (``areas``), a smoothed position outside it is moved to
its nearest walkable point: the recursion knows nothing of the plan, and a walker is never
inside a wall. Chosen on MSFT folds 0–1 among other wall-aware and process-noise variants
(skpf/ekf smoothed 3.79 → 3.65/3.64 m), reported on folds 2–3 (3.06 → 2.85, 3.16 → 2.91;
the PF's smoothed track within 0.01 m either way), docs/msft-evaluation.md.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from server.estimation.types import Estimate

if TYPE_CHECKING:  # (floorplan imports tracking.geometry, and so this package)
    from server.estimation.floorplan import Walkable


def _segments(track: Sequence[Estimate]) -> list[tuple[int, int]]:
    """[start, end) runs of one floor (of one building)."""
    out, start = [], 0
    for i in range(1, len(track)):
        if (track[i].building, track[i].floor) != (track[i - 1].building, track[i - 1].floor):
            out.append((start, i))
            start = i
    if track:
        out.append((start, len(track)))
    return out


def _predicted_cov(P: np.ndarray, Pp: np.ndarray) -> np.ndarray:
    """P_{k+1|k} with the step's process noise Q_k = P_{k+1|k} − P_{k|k} kept positive
    semi-definite (its negative eigenvalues set to 0). A Kalman filter's prediction only grows
    P, so its tracks are unchanged; a particle filter's cloud can shrink in a step (particles
    killed by a wall), and a gain C = P_{k|k} P_{k+1|k}⁻¹ above 1 would then amplify the
    differences going backwards, step after step (hundreds of metres on real walks)."""
    w, V = np.linalg.eigh(0.5 * ((Pp - P) + (Pp - P).T))
    return P + (V * np.maximum(w, 0.0)) @ V.T + 1e-12 * np.eye(len(P))


def smooth_track(track: Sequence[Estimate], areas: Mapping[tuple[int, int], Walkable] | None = None) -> list[Estimate]:
    """The RTS-smoothed track: same length, times, floors and sources; smoothed means and
    covariances. ``areas``: walkable areas by (building, floor); smoothed positions are kept in them."""
    out: list[Estimate] = list(track)
    for a, b in _segments(track):
        # time indexes: a new one at every step estimate (and at the segment's first estimate)
        index = []
        k = -1
        for i in range(a, b):
            if k < 0 or track[i].source == "step":
                k += 1
            index.append(k)
        n = k + 1
        last = [0] * n  # the filtered estimate of k: its last one
        first = [0] * n  # the predicted estimate of k: its first one
        for off, k in enumerate(index):
            last[k] = a + off
        for off in range(len(index) - 1, -1, -1):
            first[index[off]] = a + off
        xs = [np.array([track[last[k]].x, track[last[k]].y]) for k in range(n)]
        Ps = [np.array(track[last[k]].covariance, float) for k in range(n)]
        x_s, P_s = list(xs), list(Ps)
        for k in range(n - 2, -1, -1):
            nxt = track[first[k + 1]]
            xp = np.array([nxt.x, nxt.y])
            Pp = _predicted_cov(Ps[k], np.array(nxt.covariance, float))
            C = Ps[k] @ np.linalg.inv(Pp)
            x_s[k] = xs[k] + C @ (x_s[k + 1] - xp)
            P = Ps[k] + C @ (P_s[k + 1] - Pp) @ C.T
            P_s[k] = 0.5 * (P + P.T)
        area = (areas or {}).get((track[a].building, track[a].floor))
        if area is not None:
            x_s = list(area.nearest_inside(np.array(x_s)))
        for off, k in enumerate(index):
            e = track[a + off]
            out[a + off] = Estimate.of(e.t, x_s[k], P_s[k], e.floor, e.source, e.building)
    return out
