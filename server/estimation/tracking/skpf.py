"""SKPF: sigma-point Kalman particle filter, as DESIGN.md gives it.

``skpf`` is the self-calibrating form (``SKPFTracker`` at the end: n = 4, state
[x, y, b, s], also written out on Python floats); ``skpf-xy`` the two-state seed form described first.

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

Implementation: the state is 2-D with 4 sigma points, so a NumPy call costs more than
the arithmetic it does. ``predict`` and ``update`` are therefore written out in closed
form on Python floats (2×2 Cholesky, inverse and products), with no array allocated
per call. They compute the same quantities as the formulas above — for sigma points
shifted rigidly the unscented transform gives exactly x⁻ = x + f(d, h) and
P⁻ = P + Q, and for h(x) = x it gives S = P⁻ + R, Pxz = P⁻, so K S Kᵀ = P⁻ S⁻¹ P⁻ —
and are pinned against filterpy's ``JulierSigmaPoints``/``unscented_transform`` and a
filterpy ``KalmanFilter`` by the tests (equal to round-off).
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import JulierSigmaPoints

from server.estimation.tracking import selfcal
from server.estimation.tracking.base import Tracker, as_cov, as_mean, fix_cov_entries, register
from server.estimation.types import Fix, Step

N_STATE = 2
_POINTS = JulierSigmaPoints(N_STATE, kappa=0.0)  # stateless: shared
_WEIGHTS = np.asarray(_POINTS.Wm[1:], float)  # 1/2n each; the centre point has weight κ/(n+κ) = 0
_SQRT_N = math.sqrt(N_STATE)


def _chol2(a: float, b: float, c: float) -> tuple[float, float, float]:
    """Lower Cholesky factor (l11, l21, l22) of [[a, b], [b, c]]."""
    l11 = math.sqrt(a)
    l21 = b / l11
    return l11, l21, math.sqrt(max(c - l21 * l21, 0.0))  # round-off guard for a near-singular P


def symmetric_sigma_points(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 2n points x ± √n·(columns of chol(P)) and their equal weights 1/2n.

    The same set as filterpy's ``JulierSigmaPoints(2, kappa=0)`` without its zero-weight
    centre point (pinned by a test); the tracker itself uses the same points in closed form.
    """
    l11, l21, l22 = _chol2(float(P[0, 0]), float(P[0, 1]), float(P[1, 1]))
    r = _SQRT_N
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


def _reweighted_mean(x0: float, x1: float, p00: float, p01: float, p11: float, z0: float, z1: float, r00: float,
                     r01: float, r11: float) -> tuple[float, float, tuple[float, float, float, float]]:
    """The SKPF's posterior mean Σ w̃_i χ_i over the 4 sigma points x ± √2·(columns of chol(P))
    redrawn from the prior, w̃_i ∝ N(z; χ_i, R) normalised; returns it and the weights."""
    # Sigma points redrawn from the prior: x ± √n·(columns of chol(P)).
    l11, l21, l22 = _chol2(p00, p01, p11)
    u0, u1, v1 = _SQRT_N * l11, _SQRT_N * l21, _SQRT_N * l22
    # Likelihood N(z; χ_i, R) of each point, in the log domain: −½ (z − χ)ᵀ R⁻¹ (z − χ).
    det_r = r00 * r11 - r01 * r01
    i00, i01, i11 = r11 / det_r, -r01 / det_r, r00 / det_r
    e0, e1 = z0 - x0, z1 - x1
    lw = []
    for d0, d1 in ((e0 - u0, e1 - u1), (e0, e1 - v1), (e0 + u0, e1 + u1), (e0, e1 + v1)):
        lw.append(-0.5 * (i00 * d0 * d0 + 2.0 * i01 * d0 * d1 + i11 * d1 * d1))
    m = max(lw)
    a, b, c, e = (math.exp(v - m) for v in lw)
    total = a + b + c + e
    a, b, c, e = a / total, b / total, c / total, e / total
    # Σ w̃_i χ_i with χ = x + (u, 0-col) etc.
    return x0 + (a - c) * u0, x1 + (a - c) * u1 + (b - e) * v1, (a, b, c, e)


@register
class SKPFXYTracker(Tracker):
    name = "skpf-xy"
    # the state (mean and the upper triangle of the covariance) as plain floats; set by _set
    _x0: float
    _x1: float
    _p00: float
    _p01: float
    _p11: float

    def __init__(self, initial_mean, initial_cov, walls=None, seed=None, q: float = 0.01):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.params = {"q": float(q)}
        self._q = float(q)
        self._set(as_mean(initial_mean), as_cov(initial_cov))
        self._last_weights: tuple[float, ...] | None = None

    @property
    def last_weights(self) -> np.ndarray | None:
        """Normalised likelihood weights of the sigma points at the last update (diagnostics)."""
        return None if self._last_weights is None else np.array(self._last_weights)

    def predict(self, step: Step) -> None:
        # Sigma points of (x, P) shifted rigidly by f(d, h): their mean is x + f and their
        # spread is P again; the step noise J·diag(σd², σh²)·Jᵀ and q·I are added.
        h = math.radians(step.heading_deg)
        s, c = math.sin(h), math.cos(h)
        d = step.length_m
        vd = step.length_std_m * step.length_std_m
        vh = math.radians(step.heading_std_deg) ** 2 * d * d
        q = self._q
        self._x0 += d * s
        self._x1 += d * c
        self._p00 += s * s * vd + c * c * vh + q
        self._p01 += s * c * (vd - vh)
        self._p11 += c * c * vd + s * s * vh + q

    def update(self, fix: Fix) -> None:
        r00, r01, r11 = fix_cov_entries(fix.covariance)
        z0, z1 = float(fix.x), float(fix.y)
        x0, x1, p00, p01, p11 = self._x0, self._x1, self._p00, self._p01, self._p11
        self._x0, self._x1, self._last_weights = _reweighted_mean(x0, x1, p00, p01, p11, z0, z1, r00, r01, r11)
        # S = P⁻ + R, Pxz = P⁻, K = P⁻ S⁻¹, P⁺ = P⁻ − K S Kᵀ = P⁻ − P⁻ S⁻¹ P⁻.
        s00, s01, s11 = p00 + r00, p01 + r01, p11 + r11
        det_s = s00 * s11 - s01 * s01
        j00, j01, j11 = s11 / det_s, -s01 / det_s, s00 / det_s
        k00, k01 = p00 * j00 + p01 * j01, p00 * j01 + p01 * j11  # K = P S⁻¹
        k10, k11 = p01 * j00 + p11 * j01, p01 * j01 + p11 * j11
        self._p00 = p00 - (k00 * p00 + k01 * p01)
        self._p01 = p01 - 0.5 * ((k00 * p01 + k01 * p11) + (k10 * p00 + k11 * p01))
        self._p11 = p11 - (k10 * p01 + k11 * p11)

    def _set(self, x, P) -> None:
        x = np.asarray(x, float).reshape(2)
        P = np.asarray(P, float)
        self._x0, self._x1 = float(x[0]), float(x[1])
        self._p00, self._p01, self._p11 = float(P[0, 0]), 0.5 * (float(P[0, 1]) + float(P[1, 0])), float(P[1, 1])

    @property
    def x(self) -> np.ndarray:
        return np.array([self._x0, self._x1])

    @property
    def P(self) -> np.ndarray:
        return np.array([[self._p00, self._p01], [self._p01, self._p11]])

    @property
    def mean(self) -> np.ndarray:
        return self.x

    @property
    def covariance(self) -> np.ndarray:
        return self.P

    def reset(self, mean, cov) -> None:
        self._set(as_mean(mean), as_cov(cov))

    def _state(self) -> dict:
        return {"mean": [self._x0, self._x1], "cov": [[self._p00, self._p01], [self._p01, self._p11]]}

    def _load_state(self, state: dict) -> None:
        self._set(np.asarray(state["mean"], float), np.asarray(state["cov"], float))


def _chol4(a00: float, a01: float, a02: float, a03: float, a11: float, a12: float, a13: float, a22: float,
           a23: float, a33: float) -> tuple[tuple[float, float, float, float], ...]:
    """Columns of the lower Cholesky factor of a symmetric 4×4 matrix (its upper triangle
    given), unrolled on floats; a round-off floor keeps a near-singular P defined."""
    l00 = math.sqrt(max(a00, 1e-18))
    l10, l20, l30 = a01 / l00, a02 / l00, a03 / l00
    l11 = math.sqrt(max(a11 - l10 * l10, 1e-18))
    l21, l31 = (a12 - l20 * l10) / l11, (a13 - l30 * l10) / l11
    l22 = math.sqrt(max(a22 - l20 * l20 - l21 * l21, 1e-18))
    l32 = (a23 - l30 * l20 - l31 * l21) / l22
    l33 = math.sqrt(max(a33 - l30 * l30 - l31 * l31 - l32 * l32, 1e-18))
    return (l00, l10, l20, l30), (0.0, l11, l21, l31), (0.0, 0.0, l22, l32), (0.0, 0.0, 0.0, l33)


_SQRT_N4 = math.sqrt(selfcal.N_AUG)
_W4 = 1.0 / (2 * selfcal.N_AUG)
#: (i, k) of a 4×4 matrix's upper triangle, row by row
_UPPER4 = tuple((i, k) for i in range(4) for k in range(i, 4))


@register
class SKPFTracker(selfcal.Calibrating, Tracker):
    """Self-calibrating SKPF, state [x, y, b, s], the same algorithm in four dimensions.

    - prediction: the 8 sigma points of the posterior go through ``selfcal.move`` (no
      longer a rigid shift: each point has its own bias and scale); x⁻ and P⁻ are their
      mean and spread, plus G diag(σd², σh²) Gᵀ (G at the mean) and diag(q, q, σb², σs²);
    - update: the position's posterior mean is the seed form's, Σ w̃_i χ_i over the 2·2
      sigma points of the position marginal (x⁻[:2], P⁻[:2, :2]) with w̃_i ∝ N(z; χ_i, R);
      the bias and scale follow by their Gaussian regression on that correction,
      c⁺ = c⁻ + P_cp P_pp⁻¹ (x⁺ − x⁻) — exactly what the Kalman gain does for H = [I 0]
      (drawing all 8 sigma points instead would put 4 of them, those along b and s, on
      the prior position and hold the posterior back by their weight); K = Pxz S⁻¹ with
      S = P_pp + R and Pxz = P[:, :2] (the unscented transform of h(χ) = χ[:2], exact),
      and P = P⁻ − K S Kᵀ.
    """

    name = "skpf"

    def __init__(
        self,
        initial_mean,
        initial_cov,
        walls=None,
        seed=None,
        q: float = 0.01,
        bias0_std_deg: float = selfcal.BIAS0_STD_DEG,
        bias_walk_deg: float = selfcal.BIAS_WALK_DEG,
        scale0_std: float = selfcal.SCALE0_STD,
        scale_walk: float = selfcal.SCALE_WALK,
        **site: float,
    ):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.params = {"q": float(q), **selfcal.calibration_params(bias0_std_deg, bias_walk_deg, scale0_std,
                                                                   scale_walk), **selfcal.site_params(**site)}
        self._Q = selfcal.process_noise(self.params["q"], self.params)
        self._q_diag = [float(v) for v in np.diag(self._Q)]
        self.x, self.P = selfcal.initial_state(as_mean(initial_mean), as_cov(initial_cov), self.params)
        self._last_weights: tuple[float, ...] | None = None

    # The state is held as Python floats (``_x``: 4; ``_P``: 4 rows of 4), what predict and
    # update compute on; ``x`` and ``P`` are its arrays.
    @property
    def x(self) -> np.ndarray:
        return np.array(self._x)

    @x.setter
    def x(self, value) -> None:
        self._x = tuple(np.asarray(value, float).reshape(4).tolist())

    @property
    def P(self) -> np.ndarray:
        return np.array(self._P)

    @P.setter
    def P(self, value) -> None:
        self._P = tuple(map(tuple, np.asarray(value, float).reshape(4, 4).tolist()))

    @property
    def last_weights(self) -> np.ndarray | None:
        """Normalised likelihood weights of the position sigma points at the last update."""
        return None if self._last_weights is None else np.array(self._last_weights)

    def predict(self, step: Step) -> None:
        # Written out on Python floats (4×4 Cholesky, 8 points): a NumPy call per
        # operation would cost more than the arithmetic; pinned to filterpy's
        # JulierSigmaPoints + unscented_transform by the tests.
        h = math.radians(step.heading_deg)
        d = step.length_m
        x0, x1, x2, x3 = self._x
        (a00, a01, a02, a03), (_, a11, a12, a13), (_, _, a22, a23), (_, _, _, a33) = self._P
        pts = []
        for c0, c1, c2, c3 in _chol4(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33):
            c0, c1, c2, c3 = _SQRT_N4 * c0, _SQRT_N4 * c1, _SQRT_N4 * c2, _SQRT_N4 * c3
            for b, sc, e0, e1 in ((x2 + c2, x3 + c3, x0 + c0, x1 + c1), (x2 - c2, x3 - c3, x0 - c0, x1 - c1)):
                sd = sc * d
                pts.append((e0 + sd * math.sin(h + b), e1 + sd * math.cos(h + b), b, sc))
        m0, m1, m2, m3 = (sum(v) * _W4 for v in zip(*pts, strict=True))
        c00 = c01 = c02 = c03 = c11 = c12 = c13 = c22 = c23 = c33 = 0.0
        for p0, p1, p2, p3 in pts:  # Σ (χ − x⁻)(χ − x⁻)ᵀ, its upper triangle
            d0, d1, d2, d3 = p0 - m0, p1 - m1, p2 - m2, p3 - m3
            c00 += d0 * d0
            c01 += d0 * d1
            c02 += d0 * d2
            c03 += d0 * d3
            c11 += d1 * d1
            c12 += d1 * d2
            c13 += d1 * d3
            c22 += d2 * d2
            c23 += d2 * d3
            c33 += d3 * d3
        # + diag(q, q, σb², σs²) and G diag(σd², σh²) Gᵀ at the mean (its position block only).
        q = self._q_diag
        vd, vh = selfcal.step_input_var(step)
        sc2 = m3 * m3
        sa, ca = math.sin(h + m2), math.cos(h + m2)
        vdh = d * d * vh
        w = _W4
        c00 = w * c00 + sc2 * (sa * sa * vd + ca * ca * vdh) + q[0]
        c11 = w * c11 + sc2 * (ca * ca * vd + sa * sa * vdh) + q[1]
        c01 = w * c01 + sc2 * sa * ca * (vd - vdh)
        c02, c03, c12, c13 = w * c02, w * c03, w * c12, w * c13
        c22, c23, c33 = w * c22 + q[2], w * c23, w * c33 + q[3]
        self._x = (m0, m1, m2, m3)
        self._P = ((c00, c01, c02, c03), (c01, c11, c12, c13), (c02, c12, c22, c23), (c03, c13, c23, c33))
        self._observe_grid(step)

    def update(self, fix: Fix) -> None:
        r00, r01, r11 = fix_cov_entries(fix.covariance)
        x0, x1, x2, x3 = self._x
        P = self._P
        p00, p01, p11 = P[0][0], P[0][1], P[1][1]
        # Position: the seed form's rule on the position marginal (its 4 sigma points).
        pos0, pos1, self._last_weights = _reweighted_mean(x0, x1, p00, p01, p11, float(fix.x), float(fix.y),
                                                          r00, r01, r11)
        # Calibration: its Gaussian regression on the position's correction,
        # c += P_cp P_pp⁻¹ (x⁺ − x⁻) (what a Kalman gain does for H = [I 0]).
        det = p00 * p11 - p01 * p01
        d0, d1 = pos0 - x0, pos1 - x1
        a0, a1 = (p11 * d0 - p01 * d1) / det, (p00 * d1 - p01 * d0) / det
        b = x2 + P[2][0] * a0 + P[2][1] * a1
        sc = x3 + P[3][0] * a0 + P[3][1] * a1
        # Covariance: S = P_pp + R and Pxz = P[:, :2] (the UT of h(χ) = χ[:2], exact), so
        # P⁺ = P − K S Kᵀ = P − P[:, :2] S⁻¹ P[:2, :] (symmetric: its upper triangle, mirrored).
        s00, s01, s11 = p00 + r00, p01 + r01, p11 + r11
        det_s = s00 * s11 - s01 * s01
        i00, i01, i11 = s11 / det_s, -s01 / det_s, s00 / det_s
        K = [(row[0] * i00 + row[1] * i01, row[0] * i01 + row[1] * i11) for row in P]  # P[:, :2] S⁻¹
        n00, n01, n02, n03, n11, n12, n13, n22, n23, n33 = (
            P[i][k] - (K[i][0] * P[k][0] + K[i][1] * P[k][1]) for i, k in _UPPER4)
        self._x = (pos0, pos1, *selfcal.clamp_calibration(b, sc))
        self._P = ((n00, n01, n02, n03), (n01, n11, n12, n13), (n02, n12, n22, n23), (n03, n13, n23, n33))

    @property
    def state_mean(self) -> np.ndarray:
        return self.x

    @property
    def state_covariance(self) -> np.ndarray:
        return self.P

    @property
    def mean(self) -> np.ndarray:
        return np.array(self._x[:2])

    @property
    def covariance(self) -> np.ndarray:
        (p00, p01, _, _), (_, p11, _, _) = self._P[:2]
        return np.array(((p00, p01), (p01, p11)))

    def reset(self, mean, cov) -> None:
        self.x, self.P = selfcal.reset_position(self.x, self.P, as_mean(mean), as_cov(cov))

    def inflate(self, factor: float) -> None:
        self.P = self.P * float(factor)

    def _set_state(self, x: np.ndarray, P: np.ndarray) -> None:
        self.x, self.P = x, P

    def _floats(self) -> tuple[selfcal.Vec4, selfcal.Mat4]:
        return self._x, self._P

    def _set_floats(self, x: selfcal.Vec4, P: selfcal.Mat4) -> None:
        self._x, self._P = x, P

    def _state(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist(),
                "x": self.x.tolist(), "P": self.P.tolist(), **self._run_state()}

    def _load_state(self, state: dict) -> None:
        self._set_state(np.asarray(state["x"], float), np.asarray(state["P"], float))
        self._load_run(state)
