"""UKF: unscented Kalman filter with the step's length and heading noise propagated
through the nonlinear step model.

``ukf`` is the self-calibrating form (state [x, y, b, s], see ``selfcal``; sigma points
of the augmented [x, y, b, s, d, h]); ``ukf-xy`` the two-state seed form described here.

Prediction: sigma points (filterpy MerweScaledSigmaPoints) of the augmented vector
[x, y, d, h] ~ N([x, d, h], blockdiag(P, σd², σh²)) are pushed through
(x, y) + (d·sin h, d·cos h); filterpy's ``unscented_transform`` gives x⁻, P⁻ (+ q·I).
Update: filterpy ``UnscentedKalmanFilter.update`` with h(x) = x and R = fix.covariance,
or h(x) = ‖x − beacon‖ for a beacon range (within ``max_range_m``, wall side kept as in
the EKF). The sigma points for an update are always recomputed from the current
(x, P), so the stored state is just (x, P).
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter, unscented_transform

from server.estimation.tracking import selfcal
from server.estimation.tracking.base import Tracker, as_cov, as_mean, fix_cov, register, symmetric
from server.estimation.tracking.geometry import enforce_side
from server.estimation.tracking.measurements import fix_h, log_range, log_range_h, parse_on_wall, range_usable
from server.estimation.types import Fix, Step

_MIN_VAR = 1e-12


def _fx_none(x, dt):
    return x


class _UKFUpdates:
    """Fix and beacon-range updates of a filterpy UKF whose state starts with the position
    [x, y] (measurement models in ``measurements``); sigma points are recomputed from (x, P)
    before each, and ``_set`` stores the posterior."""

    ukf: UnscentedKalmanFilter
    params: dict[str, float]

    def _set(self, x, P) -> None:
        raise NotImplementedError

    def _prepare_update(self) -> None:
        self.ukf.sigmas_f = self.ukf.points_fn.sigma_points(self.ukf.x, self.ukf.P)

    def update(self, fix: Fix) -> None:
        self._prepare_update()
        self.ukf.update(np.asarray(fix.mean, float), R=fix_cov(fix.covariance), hx=fix_h)
        self._set(self.ukf.x, self.ukf.P)

    def update_range(self, beacon_xy, range_m: float, range_std_m: float, on_wall=None) -> bool:
        if not range_usable(range_m, range_std_m, self.params["max_range_m"]):
            return False
        beacon = np.asarray(beacon_xy, float).reshape(2)
        constraint = parse_on_wall(on_wall, np.asarray(self.ukf.x, float)[:2].copy())
        self._prepare_update()
        z, sigma = log_range(range_m, range_std_m)
        self.ukf.update(np.array([z]), R=np.array([[sigma**2]]), hx=log_range_h, beacon=beacon)
        x = np.asarray(self.ukf.x, float).copy()
        if constraint is not None:
            x[:2], _ = enforce_side(x[:2], constraint.wall, constraint.side, self.params["wall_margin_m"])
        self._set(x, self.ukf.P)
        return True


@register
class UKFXYTracker(_UKFUpdates, Tracker):
    name = "ukf-xy"
    supports_range = True

    def __init__(
        self,
        initial_mean,
        initial_cov,
        walls=None,
        seed=None,
        q: float = 0.01,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        max_range_m: float = 3.0,
        wall_margin_m: float = 0.05,
    ):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.params = {
            "q": float(q),
            "alpha": float(alpha),
            "beta": float(beta),
            "kappa": float(kappa),
            "max_range_m": float(max_range_m),
            "wall_margin_m": float(wall_margin_m),
        }
        self._aug_points = MerweScaledSigmaPoints(4, alpha=alpha, beta=beta, kappa=kappa)
        points = MerweScaledSigmaPoints(2, alpha=alpha, beta=beta, kappa=kappa)
        self.ukf = UnscentedKalmanFilter(dim_x=2, dim_z=2, dt=1.0, hx=fix_h, fx=_fx_none, points=points)
        self.ukf.x = as_mean(initial_mean)
        self.ukf.P = as_cov(initial_cov)

    def predict(self, step: Step) -> None:
        x_aug = np.array([self.ukf.x[0], self.ukf.x[1], step.length_m, math.radians(step.heading_deg)])
        P_aug = np.zeros((4, 4))
        P_aug[:2, :2] = self.ukf.P
        # A floor keeps the Cholesky factor defined when the phone reports exact steps.
        P_aug[2, 2] = max(step.length_std_m**2, _MIN_VAR)
        P_aug[3, 3] = max(math.radians(step.heading_std_deg) ** 2, _MIN_VAR)
        sig = self._aug_points.sigma_points(x_aug, P_aug)
        moved = sig[:, :2] + np.column_stack((sig[:, 2] * np.sin(sig[:, 3]), sig[:, 2] * np.cos(sig[:, 3])))
        x, P = unscented_transform(moved, self._aug_points.Wm, self._aug_points.Wc, self.params["q"] * np.eye(2))
        self._set(x, P)

    def _set(self, x, P) -> None:
        self.ukf.x = np.asarray(x, float).reshape(2).copy()
        self.ukf.P = 0.5 * (np.asarray(P, float) + np.asarray(P, float).T)

    @property
    def mean(self) -> np.ndarray:
        return self.ukf.x.copy()

    @property
    def covariance(self) -> np.ndarray:
        return self.ukf.P.copy()

    def reset(self, mean, cov) -> None:
        self._set(as_mean(mean), as_cov(cov))

    def _state(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist()}

    def _load_state(self, state: dict) -> None:
        self._set(np.asarray(state["mean"], float), np.asarray(state["cov"], float))


@register
class UKFTracker(_UKFUpdates, selfcal.FilterpyState, Tracker):
    """Self-calibrating UKF, state [x, y, b, s].

    Prediction: Merwe sigma points of [x, y, b, s, d, h] ~ N([x, d, h], blockdiag(P, σd², σh²))
    pushed through ``selfcal.move``; ``unscented_transform`` with noise diag(q, q, σb², σs²).
    Update: filterpy's ``UnscentedKalmanFilter.update`` (dim_x = 4) with h(x) = [x, y] for a
    fix or ‖[x, y] − beacon‖ for a range; sigma points recomputed from (x, P) each time."""

    name = "ukf"
    supports_range = True

    def __init__(
        self,
        initial_mean,
        initial_cov,
        walls=None,
        seed=None,
        q: float = 0.01,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        max_range_m: float = 3.0,
        wall_margin_m: float = 0.05,
        bias0_std_deg: float = selfcal.BIAS0_STD_DEG,
        bias_walk_deg: float = selfcal.BIAS_WALK_DEG,
        scale0_std: float = selfcal.SCALE0_STD,
        scale_walk: float = selfcal.SCALE_WALK,
        **site: float,
    ):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.params = {
            "q": float(q), "alpha": float(alpha), "beta": float(beta), "kappa": float(kappa),
            "max_range_m": float(max_range_m), "wall_margin_m": float(wall_margin_m),
            **selfcal.calibration_params(bias0_std_deg, bias_walk_deg, scale0_std, scale_walk),
            **selfcal.site_params(**site),
        }
        self._Q = selfcal.process_noise(self.params["q"], self.params)
        self._aug_points = MerweScaledSigmaPoints(6, alpha=alpha, beta=beta, kappa=kappa)
        points = MerweScaledSigmaPoints(4, alpha=alpha, beta=beta, kappa=kappa)
        self.ukf = UnscentedKalmanFilter(dim_x=4, dim_z=2, dt=1.0, hx=fix_h, fx=_fx_none, points=points)
        x, P = selfcal.initial_state(as_mean(initial_mean), as_cov(initial_cov), self.params)
        self._set(x, P)

    def predict(self, step: Step) -> None:
        x_aug = np.concatenate([self.ukf.x, [step.length_m, math.radians(step.heading_deg)]])
        P_aug = np.zeros((6, 6))
        P_aug[:4, :4] = self.ukf.P
        vd, vh = selfcal.step_input_var(step)
        P_aug[4, 4] = max(vd, _MIN_VAR)
        P_aug[5, 5] = max(vh, _MIN_VAR)
        sig = self._aug_points.sigma_points(x_aug, P_aug)
        moved = selfcal.move_many(sig[:, :4], sig[:, 4], sig[:, 5])
        x, P = unscented_transform(moved, self._aug_points.Wm, self._aug_points.Wc, self._Q)
        self._set(x, P)
        self._observe_grid(step)

    def _set(self, x, P) -> None:
        self.ukf.x = selfcal.clamp(np.asarray(x, float).reshape(4))
        self.ukf.P = symmetric(np.asarray(P, float))

    @property
    def _kf(self) -> UnscentedKalmanFilter:
        return self.ukf

    def reset(self, mean, cov) -> None:
        self._set(*selfcal.reset_position(self.ukf.x, self.ukf.P, as_mean(mean), as_cov(cov)))

    def inflate(self, factor: float) -> None:
        self._set(self.ukf.x, self.ukf.P * float(factor))
