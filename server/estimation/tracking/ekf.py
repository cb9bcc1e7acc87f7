"""EKF: heading and step length uncertain; fix or beacon-range measurements.

``ekf`` is the self-calibrating form (state [x, y, b, s], see ``selfcal``); ``ekf-xy``
the two-state seed form described first.

Seed form (``ekf-xy``, state [x, y]):

Prediction: x⁻ = x + f(d, h), P⁻ = P + J·diag(σd², σh²)·Jᵀ + q·I, with J the motion
Jacobian ∂f/∂(d, h) (see ``motion``).
Updates (measurement models in ``measurements``):
- ``update(fix)``: z = fix mean, H = I, R = fix.covariance (the fingerprint model's
  adaptive covariance).
- ``update_range(beacon, r, σr, on_wall)``: h(x) = ‖x − beacon‖, used only when the
  measured range is within ``max_range_m`` (3 m) of the beacon; when the beacon sits
  on a wall the posterior mean is kept on the wall's side.
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from server.estimation.tracking import selfcal
from server.estimation.tracking.base import FixInnovation, Tracker, as_cov, as_mean, fix_cov, register, symmetric
from server.estimation.tracking.geometry import enforce_side
from server.estimation.tracking.measurements import (
    MIN_RANGE_M,
    fix_H,
    fix_h,
    log_range,
    log_range_H,
    log_range_h,
    parse_on_wall,
    range_usable,
)
from server.estimation.tracking.motion import step_noise_cov
from server.estimation.types import Fix, Step, step_displacement


class _EKFUpdates:
    """Fix and beacon-range updates of a filterpy EKF whose state starts with the position
    [x, y] (measurement models in ``measurements``); ``_tidy`` keeps the state valid after each."""

    ekf: ExtendedKalmanFilter
    params: dict[str, float]

    def _tidy(self) -> None:
        raise NotImplementedError

    def update(self, fix: Fix) -> None:
        R = fix_cov(fix.covariance)
        self.ekf.update(np.asarray(fix.mean, float), fix_H, fix_h, R=R)
        self._tidy()

    def update_range(self, beacon_xy, range_m: float, range_std_m: float, on_wall=None) -> bool:
        if not range_usable(range_m, range_std_m, self.params["max_range_m"]):
            return False
        beacon = np.asarray(beacon_xy, float).reshape(2)
        x = np.array(self.ekf.x, float).reshape(-1)
        prior = x[:2].copy()
        constraint = parse_on_wall(on_wall, prior)
        if np.hypot(*(prior - beacon)) < MIN_RANGE_M:
            # exactly on the beacon the log-range Jacobian is zero (no direction): nudge along the first axis.
            x[:2] = prior + np.array([MIN_RANGE_M, 0.0])
            self.ekf.x = x
        z, sigma = log_range(range_m, range_std_m)
        self.ekf.update(
            np.array([z]),
            log_range_H,
            log_range_h,
            R=np.array([[sigma**2]]),
            args=(beacon,),
            hx_args=(beacon,),
        )
        self._tidy()
        if constraint is not None:
            x = np.array(self.ekf.x, float).reshape(-1)
            x[:2], _ = enforce_side(x[:2], constraint.wall, constraint.side, self.params["wall_margin_m"])
            self.ekf.x = x
        return True


@register
class EKFXYTracker(_EKFUpdates, Tracker):
    name = "ekf-xy"
    supports_range = True

    def __init__(
        self,
        initial_mean,
        initial_cov,
        walls=None,
        seed=None,
        q: float = 0.01,
        max_range_m: float = 3.0,
        wall_margin_m: float = 0.05,
    ):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.ekf = ExtendedKalmanFilter(dim_x=2, dim_z=2, dim_u=2)
        self.ekf.x = as_mean(initial_mean)
        self.ekf.P = as_cov(initial_cov)
        self.ekf.F = np.eye(2)
        self.ekf.B = np.eye(2)
        self.params = {"q": float(q), "max_range_m": float(max_range_m), "wall_margin_m": float(wall_margin_m)}

    def predict(self, step: Step) -> None:
        self.ekf.Q = step_noise_cov(step) + self.params["q"] * np.eye(2)
        self.ekf.predict(u=step_displacement(step.length_m, step.heading_deg))
        self._tidy()

    def _tidy(self) -> None:
        self.ekf.P = 0.5 * (self.ekf.P + self.ekf.P.T)

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.ekf.x, float).reshape(2).copy()

    @property
    def covariance(self) -> np.ndarray:
        return np.asarray(self.ekf.P, float).copy()

    def reset(self, mean, cov) -> None:
        self.ekf.x = as_mean(mean)
        self.ekf.P = as_cov(cov)

    def _state(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist()}

    def _load_state(self, state: dict) -> None:
        self.ekf.x = np.asarray(state["mean"], float).reshape(2)
        self.ekf.P = np.asarray(state["cov"], float).reshape(2, 2)


#: state length of the EKF that carries the walk's fix offset [x, y, b, s, oₓ, o_y]
N_OFFSET = selfcal.N_AUG + 2
#: 1: the EKF estimates the walk's fix offset from fixes that carry a walk share; 2: it considers the
#: offset without estimating it; 0 (default): neither. Both opt-in (docs/msft-evaluation.md, "The
#: map's walk share and the walk's fix offset" and "The walk's fix offset considered"): 1 failed its
#: report on MSFT folds 2–3 (3.14 → 3.63 m, 4.09 → 4.88: one walk's offset learned wrong from its first
#: fixes); 2 takes a calibrated phone's EKF below its own PDR on both halves (folds 0–1 4.09 → 3.18 m
#: against PDR 3.23, folds 2–3 3.14 → 2.84 against 3.21) but a site-calibrated one from 4.09 to 5.24 on
#: folds 2–3 (fixes known to share their error correct a compass 45° off too slowly)
WALK_OFFSET = 0.0
#: ``walk_offset`` 2: the walk's fix offset is *considered* (Schmidt–Kalman), not estimated
CONSIDER_OFFSET = 2.0


def offset_H(x: np.ndarray) -> np.ndarray:
    """Jacobian of ``offset_h``: [I₂ 0 0 I₂]."""
    H = np.zeros((2, len(x)))
    H[:, :2] = H[:, 4:6] = np.eye(2)
    return H


def offset_h(x: np.ndarray) -> np.ndarray:
    """A fix that shares the walk's offset measures position + offset."""
    return x[:2] + x[4:6]


@register
class EKFTracker(_EKFUpdates, selfcal.FilterpyState, Tracker):
    """Self-calibrating EKF, state [x, y, b, s] (heading bias in radians, step scale).

    Prediction: x⁻ = f(x, d, h), P⁻ = F P Fᵀ + G diag(σd², σh²) Gᵀ + diag(q, q, σb², σs²)
    with F = ∂f/∂x and G = ∂f/∂(d, h) at the prior mean (``selfcal.jacobians``).
    Updates: filterpy's ``ExtendedKalmanFilter.update`` with H = [I 0] for a fix, or
    H = [(x − beacon)ᵀ/‖x − beacon‖ 0] for a beacon range (as the seed form); the bias is
    then wrapped and the scale kept in range.

    **The walk's fix offset** (a fix with ``shared_share`` ρ > 0, the map's measured walk share):
    a fingerprint map's fixes along one walk share part of their error, and a filter that takes
    each fix's error as new believes the shared part many times over and is pulled onto it (on
    the MSFT walks a calibrated phone's EKF did 27 % worse than its own PDR). At the first such
    fix the state grows by the walk's offset o = [oₓ, o_y], prior N(0, ρ·R), constant along the
    walk; every such fix is then z = p + o + v, v ~ N(0, (1 − ρ)·R), so the filter learns the
    walk's offset from its first fixes and keeps its dead reckoning where the fixes agree on a
    shift. With ``walk_offset`` 2 (``CONSIDER_OFFSET``) o is *considered*, not estimated
    (Schmidt–Kalman, `_hold_offset`): the filter knows what the walk's fixes have in common, so a
    run of them stops shrinking its covariance as if each were new, but it never learns an offset
    the first fixes' noise could fake. Fixes with ρ 0 or unknown (None), or ``walk_offset`` 0 (the
    default, ``WALK_OFFSET``), are z = p + v as before; a reset drops o."""

    name = "ekf"
    supports_range = True

    def __init__(
        self,
        initial_mean,
        initial_cov,
        walls=None,
        seed=None,
        q: float = 0.01,
        max_range_m: float = 3.0,
        wall_margin_m: float = 0.05,
        bias0_std_deg: float = selfcal.BIAS0_STD_DEG,
        bias_walk_deg: float = selfcal.BIAS_WALK_DEG,
        scale0_std: float = selfcal.SCALE0_STD,
        scale_walk: float = selfcal.SCALE_WALK,
        walk_offset: float = WALK_OFFSET,
        **site: float,
    ):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.params = {"q": float(q), "max_range_m": float(max_range_m), "wall_margin_m": float(wall_margin_m),
                       **selfcal.calibration_params(bias0_std_deg, bias_walk_deg, scale0_std, scale_walk),
                       **selfcal.finite_nonnegative(walk_offset=walk_offset),
                       **selfcal.site_params(**site)}
        self._Q = selfcal.process_noise(self.params["q"], self.params)
        self._offset_prior: np.ndarray | None = None
        self.ekf = ExtendedKalmanFilter(dim_x=4, dim_z=2)
        self.ekf.x, self.ekf.P = selfcal.initial_state(as_mean(initial_mean), as_cov(initial_cov), self.params)

    def predict(self, step: Step) -> None:
        x = np.asarray(self.ekf.x, float)
        h = math.radians(step.heading_deg)
        F4, G4 = selfcal.jacobians(x, step.length_m, h)
        vd, vh = selfcal.step_input_var(step)
        n = len(x)
        F, G, Q = np.eye(n), np.zeros((n, 2)), np.zeros((n, n))  # (o is constant along the walk)
        F[:4, :4], G[:4], Q[:4, :4] = F4, G4, self._Q
        x_new = x.copy()
        x_new[:4] = selfcal.move(x[:4], step.length_m, h)
        self.ekf.x = x_new
        self.ekf.P = symmetric(F @ self.ekf.P @ F.T + (G * [vd, vh]) @ G.T + Q)
        self._observe_grid(step)
        self._hold_offset()

    def _hold_offset(self) -> None:
        """With ``walk_offset`` 2 (consider) the walk's offset is accounted for, never estimated:
        after every update its mean is 0 again and its covariance its prior, while the position's
        cross-covariance with it keeps what the fixes had in common (Schmidt–Kalman)."""
        if not self._considers_offset:
            return
        x, P = np.array(self.ekf.x, float).reshape(-1), np.array(self.ekf.P, float)
        x[4:] = 0.0
        P[4:, 4:] = self._offset_prior
        self.ekf.x, self.ekf.P = x, P

    @property
    def _considers_offset(self) -> bool:
        """Whether the state carries an offset that is considered (``walk_offset`` 2), not estimated."""
        return self.params["walk_offset"] == CONSIDER_OFFSET and self._offset_prior is not None

    def _share(self, fix: Fix) -> float:
        """The share ρ of ``fix``'s R taken as the walk's offset (0 with ``walk_offset`` off)."""
        return (fix.shared_share or 0.0) if self.params["walk_offset"] else 0.0

    def update(self, fix: Fix) -> None:
        rho = self._share(fix)
        if rho <= 0.0:
            super().update(fix)
            return
        R = fix_cov(fix.covariance)
        if not self.has_offset:
            x, P = self.state_mean, self.state_covariance
            P6 = np.zeros((N_OFFSET, N_OFFSET))
            P6[:4, :4], P6[4:, 4:] = P, rho * R
            self._set_state(np.concatenate([x, [0.0, 0.0]]), P6)
        self.ekf.update(np.asarray(fix.mean, float), offset_H, offset_h, R=(1.0 - rho) * R)
        self._tidy()

    def fix_innovation(self, fix: Fix) -> FixInnovation:
        rho = self._share(fix)
        if rho <= 0.0 or not self.has_offset:  # (before the offset exists: its prior ρR + (1 − ρ)R = R)
            return super().fix_innovation(fix)
        x, P = self.state_mean, self.state_covariance
        H = offset_H(x)
        return FixInnovation(np.asarray(fix.mean, float) - offset_h(x), H @ P @ H.T, 1.0 - rho)

    @property
    def models_walk_offset(self) -> bool:
        return bool(self.params["walk_offset"])

    @property
    def has_offset(self) -> bool:
        """Whether the state carries the walk's fix offset (after a fix with ``shared_share`` > 0)."""
        return len(self.ekf.x) == N_OFFSET

    @property
    def fix_offset(self) -> np.ndarray | None:
        """The learned walk's fix offset [oₓ, o_y] (m), or None."""
        return self.state_mean[4:6] if self.has_offset else None

    def _set_state(self, x: np.ndarray, P: np.ndarray) -> None:
        super()._set_state(x, P)
        n = len(self.ekf.x)
        self.ekf.dim_x, self.ekf._I = n, np.eye(n)  # (filterpy's update: P = (I − KH)P(I − KH)ᵀ + KRKᵀ)
        if n != N_OFFSET:
            self._offset_prior = None
        elif self._offset_prior is None:  # the offset's prior (a stored consider state keeps it there)
            self._offset_prior = np.asarray(P, float)[4:, 4:].copy()

    def _tidy(self) -> None:
        self.ekf.x = selfcal.clamp(np.asarray(self.ekf.x, float).reshape(-1))
        self.ekf.P = symmetric(np.asarray(self.ekf.P, float))
        self._hold_offset()

    @property
    def _kf(self) -> ExtendedKalmanFilter:
        return self.ekf

    def reset(self, mean, cov) -> None:
        x, P = self.state_mean[:4], self.state_covariance[:4, :4]
        self._set_state(*selfcal.reset_position(x, P, as_mean(mean), as_cov(cov)))

    def inflate(self, factor: float) -> None:
        """P × ``factor``; a considered offset (``walk_offset`` 2) is the fixes', not the tracker's:
        its covariance stays and the cross-covariance grows by √factor (D P D, D = diag(√f·I, I):
        still positive semi-definite)."""
        P = self.state_covariance * float(factor)
        if self._considers_offset:
            P[:4, 4:] /= math.sqrt(float(factor))
            P[4:, :4] /= math.sqrt(float(factor))
        self.ekf.P = P
        self._hold_offset()
