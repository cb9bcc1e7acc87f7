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
``ekf-xy``, whose position Jacobian is I) and of the seed forms' position. The self-calibrating
filters (``ekf``, ``ukf``, ``skpf``, ``pf``) store with each estimate their whole state
[x, y, b, s], its covariance and the step that predicted it (``FullState``); a run whose
estimates all have one is smoothed over the whole state, F_k the step's Jacobian at the
filtered state (``selfcal.jacobians``) in C_k = P_{k|k} F_kᵀ P_{k+1|k}⁻¹, so a heading bias
learned late bends the path before it as that bias rather than as independent noise per step
(the PF stands in with its cloud's mean and covariance). On the held-out simulator scenarios
that took the smoothed error from 1.45–1.47 to 1.23–1.28 m with wknn fixes and from 0.75–0.77
to 0.65–0.66 with unbiased ones (``benchmarks/smoother_fullstate.py``, docs/msft-evaluation.md).
Tracks stored before the states fall back to the position. The bias is an angle: the recursion
differences it modulo 2π (a walk whose bias drifts past ±180° stores it jumping by 2π). The whole-state smoother's covariance
is served calibrated (``SMOOTHED_COV_SCALE``), and every smoothed covariance positive definite.
Every estimate of index k gets the smoothed state of k; a floor change starts a new interval.
Nothing here needs the tracker: it runs on what the server stores.

So it needs neither the filter's kind nor the steps and fixes themselves: the process noise
of step k is read off the stored covariances, Q_k = P_{k+1|k} − F_k P_{k|k} F_kᵀ (the growth from the
filtered estimate to the next step's prediction, its negative part dropped: a PF's cloud may
shrink in a step where walls kill particles, ``_predicted_cov``), and each fix enters through the scan
estimate it produced (a refused fix moved nothing there, so it moves nothing here either).
``GET /api/v1/sessions/{id}/track?smoothed=true`` serves it.

A particle filter's step is not its model's: walls kill particles, and the grid's reweighing
moves weight between biases, so the model's gain P Fᵀ P⁻¹ (with Q clipped at 0) overshoots
where the cloud was cut (its smoothed NEES 11.8 on the stress scenarios with a plan). A ``pf``
step estimate therefore carries the step's joint moments as its cloud saw them (``StepJoint``:
each particle paired with its ancestor), and the RTS uses them there (an ensemble RTS smoother,
Raanes 2016): C_k = Σ_{k,k+1} P_{k+1|k}⁻¹, x_{k|N} = m'_k + C_k (x_{k+1|N} − x_{k+1|k}),
P_{k|N} = P'_k + C_k (P_{k+1|N} − P_{k+1|k}) C_kᵀ, with m'_k, P'_k the ancestors' moments under
the weights after the step (what the survivors say the old state was). For a linear-Gaussian
step those are x_{k|k}, P_{k|k}, P Fᵀ: the RTS above. Chosen on tune/stress and MSFT folds 0–1
(docs/tracking-design.md, "The PF's RTS from its own cloud"); served ×``ENSEMBLE_COV_SCALE``.

Where the floor has a walkable area (``areas``), a smoothed position outside it is moved to
its nearest walkable point: the recursion knows nothing of the plan, and a walker is never
inside a wall. Chosen on MSFT folds 0–1 among other wall-aware and process-noise variants
(skpf/ekf smoothed 3.79 → 3.65/3.64 m), reported on folds 2–3 (3.06 → 2.85, 3.16 → 2.91;
the PF's smoothed track within 0.01 m either way), docs/msft-evaluation.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from server.estimation.tracking import selfcal
from server.estimation.tracking.base import symmetric
from server.estimation.tracking.shared_error import positive_part
from server.estimation.types import Estimate, FullState, StepJoint, TrackerFailure

if TYPE_CHECKING:  # (floorplan imports tracking.geometry, and so this package)
    from server.estimation.floorplan import Walkable


#: the whole-state smoother's position covariance is served ×1.38: the RTS covariance assumes the
#: fixes' errors independent in time, but a fingerprint map's errors persist along a walk, so the
#: smoother claims more than it gains. Fitted on the tune scenarios of benchmarks/scenario_family.py
#: with knn fixes (the mean over pf/skpf/ukf/ekf of their unscaled smoothed NEES / 2; chosen against
#: the live covariance and the RTS's own on tune and stress: docs/msft-evaluation.md, "The smoothed
#: track's covariance"). Was ×2.12 when fitted (2026-12-02, smoothed NEES 3.8–5.1 then); re-fitted by
#: the same rule on 2026-12-07 (unscaled 2.44–3.33 now; a walk share the map declares has its own
#: excess, ``_shared_excess``), which took unbiased fixes' smoothed NEES from 0.68–0.72 into [1, 4]
#: (docs/tracking-design.md, "The smoothed covariance re-fitted")
SMOOTHED_COV_SCALE = 1.38
#: the same for a particle filter's track smoothed over its cloud's own step moments (``StepJoint``),
#: fitted by the same rule on the same scenarios, the PF alone (its unscaled smoothed NEES 2.43 there);
#: 1.38 served its covariance wider than its errors (unbiased fixes' smoothed NEES 0.75–1.01 on the
#: choosing cells; docs/tracking-design.md, "The PF's RTS from its own cloud")
ENSEMBLE_COV_SCALE = 1.22
#: smallest eigenvalue (m²) of a smoothed covariance (a collapsed PF cloud's round-off can leave one negative)
MIN_VARIANCE = 1e-9


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


def _predicted_cov(FPF: np.ndarray, Pp: np.ndarray) -> np.ndarray:
    """P_{k+1|k} with the step's process noise Q_k = P_{k+1|k} − F P_{k|k} Fᵀ kept positive
    semi-definite (its negative eigenvalues set to 0); ``FPF`` is F P_{k|k} Fᵀ. A Kalman filter's
    prediction only adds noise, so its tracks are unchanged; a particle filter's cloud can
    shrink in a step (particles killed by a wall), and a gain above 1 would then amplify the
    differences going backwards, step after step (hundreds of metres on real walks)."""
    return FPF + _psd(Pp - FPF, 0.0) + 1e-12 * np.eye(len(FPF))


def _psd(A: np.ndarray, floor: float) -> np.ndarray:
    """The symmetric part of ``A`` with its eigenvalues raised to at least ``floor``."""
    w, V = np.linalg.eigh(0.5 * (A + A.T))
    return (V * np.maximum(w, floor)) @ V.T


def _rts(xs: list[np.ndarray], Ps: list[np.ndarray], xp: list[np.ndarray], Pp: list[np.ndarray],
         Fs: list[np.ndarray], difference=np.subtract,
         joints: Sequence[StepJoint | None] | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The RTS recursion over time indexes 0..n−1: filtered (xs, Ps), predicted (xp[k], Pp[k]: of k
    from k − 1; index 0 unused) and the transitions Fs[k] (k − 1 → k); ``difference`` of two states
    (the whole state's wraps its angle: ``selfcal.state_difference``). ``joints[k]``: the step
    k − 1 → k as a particle cloud saw it (``StepJoint``), used instead of the model there (``_step_gain``)."""
    x_s, P_s = list(xs), list(Ps)
    for k in range(len(xs) - 2, -1, -1):
        joint = None if joints is None else joints[k + 1]
        if joint is None:
            F = Fs[k + 1]
            FP = F @ Ps[k]
            P_pred = _predicted_cov(FP @ F.T, Pp[k + 1])
            C, x0, P0 = FP.T @ np.linalg.inv(P_pred), xs[k], Ps[k]
        else:
            C, x0, P0, P_pred = _step_gain(joint, Pp[k + 1])
        x_s[k] = x0 + C @ difference(x_s[k + 1], xp[k + 1])
        P = P0 + C @ (P_s[k + 1] - P_pred) @ C.T
        P_s[k] = symmetric(P)
        if np.linalg.eigvalsh(P_s[k])[0] < MIN_VARIANCE:  # round-off after a collapsed PF cloud
            P_s[k] = _psd(P_s[k], MIN_VARIANCE)
    return x_s, P_s


def _step_gain(joint: StepJoint, P_pred: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An ensemble RTS step (the gain, the old state's mean and covariance, the predicted covariance)
    from a particle filter's own joint moments of the step: C = Σ P_{k+1|k}⁻¹, the cloud's regression
    of its old state on its new, with the mean and covariance of the particles' ancestors under the
    weights after the step. Walls that killed particles narrowed both Σ and P_{k+1|k}, so the gain
    stays the cloud's (a model gain against a cloud the walls cut overshoots), and the old state is
    what the step's survivors say it was."""
    P_pred = symmetric(P_pred) + 1e-12 * np.eye(len(P_pred))
    C = np.linalg.solve(P_pred, np.array(joint.cross, float).T).T
    return C, np.array(joint.origin_mean, float), np.array(joint.origin_covariance, float), P_pred


def _shared_excess(estimate: Estimate, state: FullState) -> np.ndarray:
    """What the session added to the tracker's position covariance for the fixes' shared error
    (``shared_error``: the estimate's covariance less its whole state's position block, ≥ 0); the
    smoothed estimate shares that error too (later fixes carry the same offset), so it keeps it."""
    P = np.array(state.covariance, float)[:2, :2]
    excess = np.array(estimate.covariance, float) - P
    if np.max(np.abs(excess)) <= 1e-9 * np.trace(P):  # (no shared error: only round-off)
        return np.zeros((2, 2))
    positive = positive_part(excess)
    return np.zeros((2, 2)) if positive is None else positive


def _full_states(states: Sequence[FullState | None], first: list[int],
                 last: list[int]) -> tuple[list[FullState], list[FullState]] | None:
    """A segment's filtered (``last``) and predicted (``first``) whole states when it can be smoothed
    over them: every estimate has one and every time index after the first starts with the step
    that predicted it; None otherwise."""
    filtered = [f for i in last if (f := states[i]) is not None]
    predicted = [f for i in first if (f := states[i]) is not None]
    if len(filtered) < len(last) or len(predicted) < len(first) or any(p.step is None for p in predicted[1:]):
        return None
    return filtered, predicted


def _jacobian(filtered: FullState, predicted: FullState) -> np.ndarray:
    """F of the step from ``filtered`` to ``predicted`` (the step that predicted it), at ``filtered``."""
    assert predicted.step is not None
    length_m, heading_deg = predicted.step
    return selfcal.jacobians(np.array(filtered.mean), length_m, math.radians(heading_deg))[0]


def smooth_track(track: Sequence[Estimate], areas: Mapping[tuple[int, int], Walkable] | None = None,
                 states: Sequence[FullState | None] | None = None) -> list[Estimate]:
    """The RTS-smoothed track: same length, times, floors and sources; smoothed means and
    covariances. ``areas``: walkable areas by (building, floor); smoothed positions are kept in them.
    ``states``: per estimate, the self-calibrating tracker's whole state (``FullState``); a floor's
    run of estimates that all have one is smoothed over the whole state, any other over the position.
    Raises ``TrackerFailure`` when the recursion fails numerically (a singular predicted covariance)."""
    try:
        return _smooth_track(track, areas, states)
    except (np.linalg.LinAlgError, ArithmeticError) as exc:
        raise TrackerFailure(f"the track could not be smoothed ({type(exc).__name__}: {exc})") from exc


def _smooth_track(track: Sequence[Estimate], areas: Mapping[tuple[int, int], Walkable] | None,
                  states: Sequence[FullState | None] | None) -> list[Estimate]:
    """`smooth_track` without its failure's translation."""
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
        full = None if states is None else _full_states(states, first, last)
        if full is not None:
            filtered, predicted = full
            Fs = [np.eye(len(filtered[0].mean))] + [_jacobian(filtered[k - 1], predicted[k]) for k in range(1, n)]
            joints = [None] + [p.joint for p in predicted[1:]]
            x_s, P_s = _rts([np.array(f.mean) for f in filtered], [np.array(f.covariance) for f in filtered],
                            [np.array(f.mean) for f in predicted], [np.array(f.covariance) for f in predicted], Fs,
                            selfcal.state_difference, joints)
            x_s = [x[:2] for x in x_s]
            scale = ENSEMBLE_COV_SCALE if n > 1 and all(joints[1:]) else SMOOTHED_COV_SCALE
            P_s = [scale * P[:2, :2] + _shared_excess(track[i], f) for P, i, f in zip(P_s, last, filtered, strict=True)]
        else:
            fe, pe = [track[i] for i in last], [track[i] for i in first]
            x_s, P_s = _rts([np.array([e.x, e.y]) for e in fe], [np.array(e.covariance, float) for e in fe],
                            [np.array([e.x, e.y]) for e in pe], [np.array(e.covariance, float) for e in pe],
                            [np.eye(2)] * n)
        area = (areas or {}).get((track[a].building, track[a].floor))
        if area is not None:
            x_s = list(area.nearest_inside(np.array(x_s)))
        for off, k in enumerate(index):
            e = track[a + off]
            out[a + off] = Estimate.of(e.t, x_s[k], P_s[k], e.floor, e.source, e.building)
    return out
