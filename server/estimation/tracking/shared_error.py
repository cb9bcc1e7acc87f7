"""What a self-calibrating tracker's covariance leaves out: the fixes' shared error, a cold start's narrowed inputs.

A fingerprint map's fixes along one walk share part of their error (the map's measured walk
share ρ, ``Fix.shared_share``: on the MSFT walks 0.24–0.70 of a fix's whitened error is common to
fixes ≥ 10 m apart). A filter that takes each fix's error as new averages the independent parts
away and believes the shared part gone too: its covariance shrinks fix after fix while its error
stays at the shared offset (position NEES 8–14 on simulated walks whose fixes share their error,
5.7–10.9 for the PF on the MSFT walks).

This module does not change the filter (its gains, its gate, its estimates stay exactly as they
are: estimating or considering the offset in the gain lost on real walks, docs/tracking-design.md).
It computes what that filter's error covariance actually is when each fix k is
z = p + √ρₖ Lₖ u + v, with u ~ N(0, I₂) one whitened offset for the whole walk (LₖLₖᵀ = Rₖ, the
fix's covariance as the session measures it: the model's times max(the session's scale, 1)) and v
the fix's own noise — the *consider covariance*
of the Schmidt–Kalman literature, propagated with the filter's own gains. With e the error of
the tracker's state [x, y, b, s], the session keeps D = E[eeᵀ] − P (what the tracker's covariance
P leaves out) and C = E[e uᵀ]:

- a step e ← F e + w (F = ∂f/∂x at the state before it): D ← F D Fᵀ, C ← F C;
- an accepted fix with gain K = P⁻Hᵀ(HP⁻Hᵀ + R_used)⁻¹ from the prior moments (H = [I₂ 0], the
  gain of the Gaussian filters and the PF's cloud moments alike), A = I − KH:
  C ← A C + √ρ K L, D ← A D Aᵀ + √ρ (A C Lᵀ Kᵀ + K L Cᵀ Aᵀ) (the shared part's own √ρL·√ρLᵀ
  is already in the filter's R);
- a measurement sharing nothing (a landmark snap; a beacon range, with A = P⁺ P⁻⁻¹ from the
  tracker's own covariances before and after it, `measured`): D ← A D Aᵀ, C ← A C;
- a restart on a fix (cold start, floor change): the position's error is that fix's error, so
  its rows of C are √ρ L and of D what the start's covariance leaves out of the fix's (the bias
  and scale keep theirs).

The same excess counts what a tracker's deliberately narrowed inputs leave out: a cold start caps
its first fix's covariance (``COLD_START_MAX_STD_M``) and takes its fixes with a scale prior below 1
(``COLD_FIX_SCALE_PRIOR``) to follow them faster, so its covariance claims what the fixes do not
give (NEES 7.4–8.2 on MSFT folds 0–1 without an initial position). An update with R_used narrower
than the fixes' measured R (R_own × max(the session's scale, 1)) adds K (R − R_used) Kᵀ, and a start
narrower than its fix adds the difference to D: exact for a linear filter, like the rest.

The reported covariance is P + D on the position (D clipped at 0 there: the excess never makes
the report narrower than the tracker's own). Grid observations and walls are left out (each would
only shrink D further), as is a Student-t weight's widening of R: the report errs wide, never
narrow. Beacon ranges count: left out, a session whose fixes say little (a degenerate start, a
floor whose map is poor) but whose ranges place it well kept the start's excess for good (the
multi-floor crowd benchmark's ground floor reported σ ≈ 500 m on a tracker sure within 1 m, and no
estimate there ever passed the crowd gate). Known-start sessions whose fixes carry no share leave
D = C = 0 and report P exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from server.estimation.tracking.selfcal import N_AUG, jacobians
from server.estimation.types import Step


def positive_part(M: np.ndarray) -> np.ndarray | None:
    """A symmetric 2 × 2 matrix with its negative eigenvalue (if any) set to 0, in closed form
    (once per estimate); None when nothing positive is left."""
    (a, b), (_, c) = M.tolist()
    m, r = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    if m + r <= 0.0:
        return None
    if m - r >= 0.0:  # both eigenvalues ≥ 0: as it is
        return np.array(((a, b), (b, c)))
    lam = m + r  # the positive eigenvalue alone: λ·vvᵀ, v its unit eigenvector
    vx, vy = (b, lam - a) if abs(lam - a) >= abs(lam - c) else (lam - c, b)
    k = lam / (vx * vx + vy * vy)
    return np.array(((k * vx * vx, k * vx * vy), (k * vx * vy, k * vy * vy)))


def _zeros_d() -> np.ndarray:
    return np.zeros((N_AUG, N_AUG))


def _zeros_c() -> np.ndarray:
    return np.zeros((N_AUG, 2))


@dataclass
class SharedFixError:
    """The excess covariance ``D`` (4×4) and the cross-covariance ``C`` (4×2) with the walk's
    whitened fix offset (module docstring); both zero until a fix that shares its error or is
    taken narrower than measured. ``active``: whether one has been (before, D and C are zero and
    stay zero under every update, so nothing need be computed)."""

    D: np.ndarray = field(default_factory=_zeros_d)
    C: np.ndarray = field(default_factory=_zeros_c)
    active: bool = False

    def step(self, x_before: np.ndarray, step: Step) -> None:
        """A PDR step from state ``x_before`` ([x, y, b, s])."""
        F, _ = jacobians(np.asarray(x_before, float)[:N_AUG], step.length_m, math.radians(step.heading_deg))
        self.D = F @ self.D @ F.T
        self.C = F @ self.C

    def fix(self, P_prior: np.ndarray, R: np.ndarray, R_used: np.ndarray, share: float | None) -> None:
        """An accepted fix (or landmark snap) with marginal covariance ``R`` (as the session
        measures its fixes), taken by the tracker with ``R_used``, a share ``share`` of it common
        to the walk, on the tracker's prior state covariance ``P_prior`` (4×4). Where ``R_used`` is
        narrower than ``R`` (a cold start's scale prior below 1 makes it follow its fixes faster),
        the gain's K (R − R_used)Kᵀ that the tracker's covariance leaves out is added; where it is
        wider (a Student-t weight), nothing is taken away (the report errs wide)."""
        P = np.asarray(P_prior, float)
        K = P[:, :2] @ np.linalg.inv(P[:2, :2] + np.asarray(R_used, float))
        A = np.eye(N_AUG)
        A[:, :2] -= K
        D = A @ self.D @ A.T
        C = A @ self.C
        narrowed = positive_part(np.asarray(R, float) - np.asarray(R_used, float))
        if narrowed is not None:
            self.active = True
            D = D + K @ narrowed @ K.T
        rho = share or 0.0
        if rho > 0.0:
            self.active = True
            KL = math.sqrt(rho) * K @ np.linalg.cholesky(np.asarray(R, float))
            cross = C @ KL.T  # (A C)(√ρ K L)ᵀ: uses C before this fix's own share is added
            D = D + cross + cross.T
            C = C + KL
        self.D, self.C = 0.5 * (D + D.T), C

    def measured(self, P_prior: np.ndarray, P_post: np.ndarray) -> None:
        """A measurement sharing nothing with the fixes (a beacon range) that took the tracker's
        state covariance from ``P_prior`` to ``P_post`` (4×4): the excess goes as the tracker's own
        did, D ← A D Aᵀ, C ← A C with A = P_post P_prior⁻¹ — the update's I − K H for a Kalman
        filter, its statistical linearisation for a UKF or a cloud, whatever the measurement model.
        (A linearised gain instead would take a range from D that a UKF whose sigma points lie far
        beyond the beacon never took from itself: the report would err narrow.) A singular prior
        leaves D and C as they are (the report errs wide)."""
        try:
            At = np.linalg.solve(np.asarray(P_prior, float), np.asarray(P_post, float).T)
        except np.linalg.LinAlgError:
            return
        A = At.T
        D = A @ self.D @ A.T
        self.D, self.C = 0.5 * (D + D.T), A @ self.C

    def restart(self, R: np.ndarray, share: float | None, R_start: np.ndarray | None = None) -> None:
        """The position restarted on a fix with marginal covariance ``R`` and shared ``share``:
        its error is that fix's, √ρ L u plus the fix's own noise; started with ``R_start`` (a cold
        start caps it), the position's D is what that leaves out of ``R``."""
        self.D[:2, :] = 0.0
        self.D[:, :2] = 0.0
        R = np.asarray(R, float)
        self.C[:2] = math.sqrt(share) * np.linalg.cholesky(R) if share else 0.0
        narrowed = None if R_start is None else positive_part(R - np.asarray(R_start, float))
        if narrowed is not None:
            self.D[:2, :2] = narrowed
        self.active = self.active or bool(share) or narrowed is not None

    def reported(self, P_pos: np.ndarray) -> np.ndarray:
        """The position covariance to report: the tracker's ``P_pos`` + D's position block with
        its negative eigenvalue (if any) set to 0."""
        excess = positive_part(self.D[:2, :2])
        return np.asarray(P_pos, float) if excess is None else np.asarray(P_pos, float) + excess

    def to_dict(self) -> dict[str, list] | None:
        """JSON form (None when nothing is carried)."""
        return {"D": self.D.tolist(), "C": self.C.tolist()} if self.active else None

    @classmethod
    def from_dict(cls, d: dict | None) -> SharedFixError:
        """Inverse of ``to_dict``; None (a state stored without it) gives zeros."""
        if d is None:
            return cls()
        return cls(np.asarray(d["D"], float).reshape(N_AUG, N_AUG), np.asarray(d["C"], float).reshape(N_AUG, 2), True)
