"""SKPF: sigma-point Kalman particle filter, as DESIGN.md gives it.

With n = 2 (state [x, y]):
- the 2n symmetric sigma points χ_i = x ± √n·(columns of √P), weights 1/2n, are drawn
  from the posterior (filterpy ``JulierSigmaPoints`` with κ = 0, whose centre point has
  weight 0 and is dropped);
- prediction propagates each through the step model, χ_i ← χ_i + (d·sin h, d·cos h);
  x⁻ = Σ χ_i/2n, P⁻ = Σ (χ_i − x⁻)(χ_i − x⁻)ᵀ/2n + J·diag(σd², σh²)·Jᵀ + q·I
  (the step's own noise enters as process noise: the sigma points are shifted rigidly);
- at an update the sigma points are redrawn from the prior (x⁻, P⁻); filterpy's
  ``unscented_transform`` of h(χ_i) gives ẑ and S = Σ w (Z_i − ẑ)(Z_i − ẑ)ᵀ + R,
  Pxz = Σ w (χ_i − x⁻)(Z_i − ẑ)ᵀ, K = Pxz S⁻¹;
- the posterior mean is Σ w̃_i χ_i with w̃_i ∝ N(z; h(χ_i), R) normalised, and
  P = P⁻ − K S Kᵀ.
State between calls is just (x, P); the sigma points follow from it.
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import JulierSigmaPoints, unscented_transform

from server.estimation.tracking.base import Tracker, as_cov, as_mean, fix_cov, register
from server.estimation.tracking.motion import step_noise_cov
from server.estimation.types import Fix, Step, step_displacement

N_STATE = 2
_POINTS = JulierSigmaPoints(N_STATE, kappa=0.0)  # stateless: shared
_WEIGHTS = np.asarray(_POINTS.Wm[1:], float)  # 1/2n each; the centre point has weight κ/(n+κ) = 0


def symmetric_sigma_points(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 2n points x ± √n·(columns of chol(P)) and their equal weights 1/2n.

    The same set as filterpy's ``JulierSigmaPoints(2, kappa=0)`` without its zero-weight
    centre point (pinned by a test), with the 2×2 Cholesky factor written out: at this
    size filterpy's scipy call costs more than the whole filter step.
    """
    a, b, c = float(P[0, 0]), float(P[0, 1]), float(P[1, 1])
    l11 = math.sqrt(a)
    l21 = b / l11
    l22 = math.sqrt(max(c - l21 * l21, 0.0))  # round-off guard for a near-singular P
    r = math.sqrt(N_STATE)
    x0, x1 = float(x[0]), float(x[1])
    sigmas = np.array(
        [
            [x0 + r * l11, x1 + r * l21],
            [x0, x1 + r * l22],
            [x0 - r * l11, x1 - r * l21],
            [x0, x1 - r * l22],
        ]
    )
    return sigmas, _WEIGHTS


@register
class SKPFTracker(Tracker):
    name = "skpf"

    def __init__(self, initial_mean, initial_cov, walls=None, seed=None, q: float = 0.01):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.params = {"q": float(q)}
        self.x = as_mean(initial_mean)
        self.P = as_cov(initial_cov)
        #: normalised likelihood weights of the last update (diagnostics)
        self.last_weights: np.ndarray | None = None

    def predict(self, step: Step) -> None:
        sigmas, w = symmetric_sigma_points(self.x, self.P)
        sigmas = sigmas + step_displacement(step.length_m, step.heading_deg)
        Q = step_noise_cov(step) + self.params["q"] * np.eye(2)
        x, P = unscented_transform(sigmas, w, w, Q)
        self._set(x, P)

    def update(self, fix: Fix) -> None:
        R = fix_cov(fix.covariance)
        z = np.asarray(fix.mean, float)
        sigmas, w = symmetric_sigma_points(self.x, self.P)  # redrawn from the prior
        Z = sigmas  # h(x) = x for a position fix
        z_hat, S = unscented_transform(Z, w, w, R)
        Pxz = (w[:, None] * (sigmas - self.x)).T @ (Z - z_hat)
        K = Pxz @ np.linalg.inv(S)
        # Gaussian likelihood of the fix for each sigma point, normalised (log domain).
        diff = z - Z
        maha = np.einsum("ij,jk,ik->i", diff, np.linalg.inv(R), diff)
        lw = -0.5 * maha
        lik = np.exp(lw - lw.max())
        lik /= lik.sum()
        self.last_weights = lik
        self._set(lik @ sigmas, self.P - K @ S @ K.T)

    def _set(self, x, P) -> None:
        self.x = np.asarray(x, float).reshape(2).copy()
        P = np.asarray(P, float)
        self.P = 0.5 * (P + P.T)

    @property
    def mean(self) -> np.ndarray:
        return self.x.copy()

    @property
    def covariance(self) -> np.ndarray:
        return self.P.copy()

    def reset(self, mean, cov) -> None:
        self._set(as_mean(mean), as_cov(cov))

    def _state(self) -> dict:
        return {"mean": self.x.tolist(), "cov": self.P.tolist()}

    def _load_state(self, state: dict) -> None:
        self._set(np.asarray(state["mean"], float), np.asarray(state["cov"], float))
