"""Self-calibrating PDR: the step model of the augmented (four-state) trackers.

State ``[x, y, b, s]``: position (site metres), the PDR's heading bias ``b`` (radians,
added to the phone's heading) and its step-length scale ``s`` (multiplies the phone's
length). A step of reported length d along reported heading h moves the walker by

    f(x, d, h) = (x + s·d·sin(h + b), y + s·d·cos(h + b), b, s)

and ``b`` and ``s`` drift as slow random walks (``bias_walk_deg`` and ``scale_walk`` of
standard deviation per step). Fixes measure ``[x, y]`` only; because a bias bends the
track away from the fixes in a way that correlates with the heading, the filters learn
``b`` and ``s`` from the fixes, and the dead reckoning between fixes is corrected.

Why: real PDR heading error is mostly a bias that accumulates (a magnetometer offset, a
phone held askew, gyro drift), so an independent-noise model lets the error grow like n
while the covariance grows like √n, and the innovation gate then refuses the very fixes
that would correct it.

The default noise levels come from data (``benchmarks/pdr_noise.py`` on the shared MSFT
walks, then a choice on the tune scenarios of ``benchmarks/scenario_family.py``; the
README's "Tracking design" gives the figures); the phone's own ``length_std_m`` and
``heading_std_deg`` are the white per-step part.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, TypeVar

import numpy as np

from server.estimation.building_grid import grid_direction_deg
from server.estimation.types import Area, Step, StepJoint

#: prior standard deviation of the heading bias at a session's start (degrees)
BIAS0_STD_DEG = 10.0
#: random-walk standard deviation of the heading bias per step (degrees)
BIAS_WALK_DEG = 1.0
#: prior standard deviation of the step-length scale (1 = the phone's lengths are right)
SCALE0_STD = 0.1
#: random-walk standard deviation of the step-length scale per step
SCALE_WALK = 0.003
#: the scale is kept in this range (a filter may not learn a walker who does not move)
SCALE_RANGE = (0.5, 2.0)

N_AUG = 4

#: the building's grid as a heading reference (``Calibrating._observe_grid``): σ of the observation
#: (degrees; 0 = off), the gate on a run's offset from the nearest grid direction, and every how many
#: steps of a straight run it is observed (chosen on MSFT folds 0–1 and the tune and stress splits
#: among once per run at 4 or 8 steps and every 8 or 16 steps, gates 15° and 20°; reported on MSFT
#: folds 2–3 and held-out draw 112–127: docs/msft-evaluation.md, "The building's grid, once per
#: straight run")
GRID_SIGMA_DEG = 3.0
GRID_GATE_DEG = 20.0
GRID_STEPS = 8
#: a straight run: consecutive steps whose reported heading stays within this of the run's mean (degrees)
STRAIGHT_DEG = 10.0
#: where the fingerprint model looks for a fix (``Calibrating.search_region``): within this many of the
#: tracker's largest position σ plus this margin (m) of its estimate; 0 σ = anywhere. Chosen on the
#: stress/tune splits' draws 100–111 and MSFT folds 0–1 among (3, 10) and (3, 20) (docs/tracking-design.md,
#: "Where the fingerprint model looks")
SEARCH_SIGMAS = 3.0
SEARCH_MARGIN_M = 10.0


def finite_nonnegative(**values: float) -> dict[str, float]:
    """``values`` as floats; ValueError naming the first that is not a finite number ≥ 0."""
    for k, v in values.items():
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{k} must be a finite number ≥ 0")
    return {k: float(v) for k, v in values.items()}


def calibration_params(
    bias0_std_deg: float = BIAS0_STD_DEG,
    bias_walk_deg: float = BIAS_WALK_DEG,
    scale0_std: float = SCALE0_STD,
    scale_walk: float = SCALE_WALK,
) -> dict[str, float]:
    return finite_nonnegative(bias0_std_deg=bias0_std_deg, bias_walk_deg=bias_walk_deg, scale0_std=scale0_std,
                              scale_walk=scale_walk)


def grid_params(grid_sigma_deg: float = GRID_SIGMA_DEG, grid_gate_deg: float = GRID_GATE_DEG,
                grid_steps: float = GRID_STEPS) -> dict[str, float]:
    out = finite_nonnegative(grid_sigma_deg=grid_sigma_deg, grid_gate_deg=grid_gate_deg, grid_steps=grid_steps)
    out["grid_steps"] = float(max(1, round(out["grid_steps"])))
    return out


def search_params(search_sigmas: float = SEARCH_SIGMAS, search_margin_m: float = SEARCH_MARGIN_M) -> dict[str, float]:
    """Where the fingerprint model may look (``Calibrating.search_region``), checked finite and ≥ 0."""
    return finite_nonnegative(search_sigmas=search_sigmas, search_margin_m=search_margin_m)


def site_params(search_sigmas: float = SEARCH_SIGMAS, search_margin_m: float = SEARCH_MARGIN_M,
                **grid: float) -> dict[str, float]:
    """``grid_params`` and ``search_params`` together: what a Gaussian filter takes from its site."""
    return {**grid_params(**grid), **search_params(search_sigmas, search_margin_m)}


Angle = TypeVar("Angle", float, np.ndarray)


def wrap_deg(a: Angle, period: float = 360.0) -> Angle:
    """``a`` (a number, or an array of them) wrapped to [−period/2, period/2)."""
    return (a + period / 2) % period - period / 2


class StraightRun(NamedTuple):
    """The current run of straight steps: their mean reported heading (degrees) and count
    (a tuple: made at every step)."""

    mean_deg: float = 0.0
    n: int = 0

    def extended(self, heading_deg: float) -> StraightRun:
        """This run with one more step, or a new run from it when it turns more than ``STRAIGHT_DEG``."""
        off = wrap_deg(heading_deg - self.mean_deg)
        if self.n == 0 or abs(off) > STRAIGHT_DEG:
            return StraightRun(wrap_deg(heading_deg), 1)
        return StraightRun(wrap_deg(self.mean_deg + off / (self.n + 1)), self.n + 1)


def initial_state(mean2: np.ndarray, cov2: np.ndarray, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """[x, y, 0, 1] and blockdiag(P, σb0², σs0²) (floors keep P positive definite)."""
    x = np.array([mean2[0], mean2[1], 0.0, 1.0])
    P = np.zeros((N_AUG, N_AUG))
    P[:2, :2] = cov2
    P[2, 2] = max(math.radians(params["bias0_std_deg"]) ** 2, 1e-12)
    P[3, 3] = max(params["scale0_std"] ** 2, 1e-12)
    return x, P


def reset_position(x: np.ndarray, P: np.ndarray, mean2: np.ndarray, cov2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A restart of the position (snap, floor change) keeps what was learned of b and s."""
    x = x.copy()
    P = P.copy()
    x[:2] = mean2
    P[:2, :] = 0.0
    P[:, :2] = 0.0
    P[:2, :2] = cov2
    return x, P


def move(x: np.ndarray, d: float, h_rad: float) -> np.ndarray:
    """f(x, d, h) for one state (a copy)."""
    a = h_rad + x[2]
    sd = x[3] * d
    return np.array([x[0] + sd * math.sin(a), x[1] + sd * math.cos(a), x[2], x[3]])


def move_many(X: np.ndarray, d, h_rad) -> np.ndarray:
    """f for rows of states (n, 4); ``d`` and ``h_rad`` scalars or (n,) arrays."""
    a = h_rad + X[:, 2]
    sd = X[:, 3] * d
    out = X.copy()
    out[:, 0] += sd * np.sin(a)
    out[:, 1] += sd * np.cos(a)
    return out


def jacobians(x: np.ndarray, d: float, h_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """F = ∂f/∂x (4×4) and G = ∂f/∂(d, h) (4×2) at ``x``."""
    a = h_rad + x[2]
    sa, ca = math.sin(a), math.cos(a)
    s = x[3]
    F = np.eye(N_AUG)
    F[0, 2], F[0, 3] = s * d * ca, d * sa
    F[1, 2], F[1, 3] = -s * d * sa, d * ca
    G = np.array([[s * sa, s * d * ca], [s * ca, -s * d * sa], [0.0, 0.0], [0.0, 0.0]])
    return F, G


def step_input_var(step: Step) -> tuple[float, float]:
    """(σd², σh²) of the step's white noise, σh in radians."""
    return step.length_std_m**2, math.radians(step.heading_std_deg) ** 2


def process_noise(q: float, params: dict) -> np.ndarray:
    """diag(q, q, σb², σs²): position jitter and the random walks of b and s per step."""
    return np.diag([q, q, math.radians(params["bias_walk_deg"]) ** 2, params["scale_walk"] ** 2])


def clamp_calibration(b: float, s: float) -> tuple[float, float]:
    """Bias wrapped to (−π, π], scale kept in ``SCALE_RANGE``."""
    return math.remainder(b, 2 * math.pi), min(max(s, SCALE_RANGE[0]), SCALE_RANGE[1])


def state_difference(a, b) -> np.ndarray:
    """a − b for states [x, y, b, s], the bias part wrapped to (−π, π]: the trackers keep b in
    (−π, π], so a bias drifting past ±180° is stored jumping by 2π, and it is still one angle."""
    d = np.asarray(a, float) - np.asarray(b, float)
    d[2] = math.remainder(float(d[2]), 2 * math.pi)
    return d


def clamp(x: np.ndarray) -> np.ndarray:
    """``clamp_calibration`` on a state [x, y, b, s] (a new array)."""
    x = np.asarray(x, float).copy()
    x[2], x[3] = clamp_calibration(float(x[2]), float(x[3]))
    return x


Vec4 = tuple[float, ...]
Mat4 = tuple[tuple[float, ...], ...]


def observe_bias(x: Vec4, P: Mat4, innovation: float, var: float) -> tuple[Vec4, Mat4]:
    """A scalar Kalman update of [x, y, b, s] by an observation of b (innovation z − b̂, noise
    variance ``var``): x += K·innovation, P −= K·P[2, :] with K = P[:, 2] / (P[2, 2] + var), b and
    s clamped as everywhere. Written out on Python floats from P's upper triangle (the result is
    symmetric by construction; NumPy calls on 4 numbers would cost 5× the arithmetic)."""
    (p00, p01, c0, p03), (_, p11, c1, p13), (_, _, c2, c3), (_, _, _, p33) = P
    g = 1.0 / (c2 + var)
    k0, k1, k2, k3 = c0 * g, c1 * g, c2 * g, c3 * g
    n00, n01, n02, n03 = p00 - c0 * k0, p01 - c0 * k1, c0 - c0 * k2, p03 - c0 * k3
    n11, n12, n13 = p11 - c1 * k1, c1 - c1 * k2, p13 - c1 * k3
    n22, n23, n33 = c2 - c2 * k2, c3 - c2 * k3, p33 - c3 * k3
    x0, x1, b, sc = x
    return ((x0 + k0 * innovation, x1 + k1 * innovation, *clamp_calibration(b + k2 * innovation, sc + k3 * innovation)),
            ((n00, n01, n02, n03), (n01, n11, n12, n13), (n02, n12, n22, n23), (n03, n13, n23, n33)))


def observe_bias_array(x: np.ndarray, P: np.ndarray, innovation: float, var: float) -> tuple[np.ndarray, np.ndarray]:
    """``observe_bias`` on a state that carries more than [x, y, b, s] (an EKF with the walk's fix
    offset): the same scalar Kalman update, in NumPy."""
    K = P[:, 2] / (P[2, 2] + var)
    return clamp(x + K * innovation), P - np.outer(K, P[2, :])


class Calibrating:
    """Mixin of the augmented trackers: what they have learned, for reports and tests; and the
    building's grid as a heading reference: the straight run and when it observes the grid
    (``_grid_offset``), and the Gaussian filters' update (``_observe_grid``; the PF weighs its
    particles instead)."""

    augmented = True
    params: dict[str, Any]
    walls: np.ndarray
    survey_grid_deg: float | None
    _run = StraightRun()
    #: a particle filter's last step as its cloud saw it (``StepJoint``; None for the Gaussian filters,
    #: whose smoother gain is their model's); not stored: it goes with the step's estimate
    step_joint: StepJoint | None = None
    #: the grid direction of the walls it was computed for (``grid_direction_deg`` reads every wall)
    _grid_walls: np.ndarray | None = None
    _grid_deg: float | None = None

    def _set_state(self, x: np.ndarray, P: np.ndarray) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _grid_offset(self, step: Step) -> float | None:
        """Extend the straight run by ``step``; when an observation of the grid is due (the run has
        grown by ``grid_steps``, ``grid_sigma_deg`` > 0, the floor has a grid: its walls', else its
        survey's, ``Tracker.survey_grid_deg``), the grid direction minus the run's mean heading
        (degrees, to be wrapped with b mod 90°), else None."""
        p = self.params
        if p["grid_sigma_deg"] <= 0:
            return None
        self._run = self._run.extended(step.heading_deg)
        if self._run.n % int(p["grid_steps"]):
            return None
        if self._grid_walls is not self.walls:
            self._grid_walls, self._grid_deg = self.walls, grid_direction_deg(self.walls)
        grid = self._grid_deg if self._grid_deg is not None else self.survey_grid_deg
        if grid is None:
            return None
        return grid - self._run.mean_deg

    def _observe_grid(self, step: Step) -> None:
        """Heuristic drift elimination per straight run (``grid_sigma_deg`` > 0, on a floor whose
        walls have a grid): in a rectilinear building people walk along its grid, so each time a
        run of straight steps has grown by ``grid_steps``, its corrected heading (the run's mean
        heading + b) within ``grid_gate_deg`` of a grid direction observes b with σ =
        ``grid_sigma_deg``: a scalar Kalman update, position and scale following through their
        correlation. Per run, not per step (the form tried before, which lost walks whose bias
        passed a wrong grid direction): a corridor is a few observations, not one per step, and
        a turn (any step more than ``STRAIGHT_DEG`` off the run's mean) starts a new run."""
        offset = self._grid_offset(step)
        if offset is None:
            return
        p = self.params
        x, P = self._floats()
        r = wrap_deg(offset - math.degrees(x[2]), 90.0)
        if abs(r) > p["grid_gate_deg"]:
            return
        self._observe_bias(math.radians(r), math.radians(p["grid_sigma_deg"]) ** 2, x, P)

    def _observe_bias(self, innovation: float, var: float, x: Vec4 | None = None, P: Mat4 | None = None) -> None:
        """A scalar Kalman update of the state by an observation of b (``innovation`` z − b̂ in
        radians, noise variance ``var``); ``x``, ``P``: the state as ``_floats`` gives it, if at hand."""
        if x is None or P is None:
            x, P = self._floats()
        if len(x) == N_AUG:
            self._set_floats(*observe_bias(x, P, innovation, var))
        else:
            self._set_state(*observe_bias_array(self.state_mean, self.state_covariance, innovation, var))

    def observe_heading(self, step: Step, heading_deg: float, std_deg: float) -> None:
        """The walker's true direction at ``step`` is ``heading_deg`` (σ ``std_deg``, beside the
        step's own white heading noise): an observation of b = heading_deg − the step's reported
        heading. A session's ``initial`` heading with its own σ comes in here at the first step: a
        phone that knows which way it walks at its start, independently of its compass, tells the
        tracker its heading bias, which the fixes otherwise have to teach it."""
        z = math.radians(heading_deg - step.heading_deg)
        var = math.radians(std_deg) ** 2 + math.radians(step.heading_std_deg) ** 2
        self._observe_bias(math.remainder(z - float(self.state_mean[2]), 2 * math.pi), var)

    def search_region(self) -> Area | None:
        """The fingerprint model looks within ``search_sigmas`` × the largest position σ +
        ``search_margin_m`` of the estimate (None: anywhere, ``search_sigmas`` 0). A scan that
        resembles a far part of the building gives the best match near the walker instead of a fix
        tens of metres off, which the gate would refuse or the fix-noise scale learn to distrust
        (with it every other fix); the σ term keeps an uncertain tracker's fixes free to pull it
        back, and the gate's widening after refused fixes widens the search with it."""
        k = self.params["search_sigmas"]
        if k <= 0:
            return None
        sd = math.sqrt(max(float(np.linalg.eigvalsh(self.state_covariance[:2, :2])[-1]), 0.0))
        x, y = (float(v) for v in self.state_mean[:2])
        return Area(x, y, k * sd + self.params["search_margin_m"])

    def _floats(self) -> tuple[Vec4, Mat4]:
        """[x, y, b, s] and its covariance as Python floats (what the grid's update computes on)."""
        return tuple(self.state_mean.tolist()), tuple(map(tuple, self.state_covariance.tolist()))

    def _set_floats(self, x: Vec4, P: Mat4) -> None:
        self._set_state(np.array(x), np.array(P))

    def _run_state(self) -> dict:
        return {"run": [self._run.mean_deg, self._run.n]} if self._run.n else {}

    def _load_run(self, state: dict) -> None:
        run = state.get("run")
        self._run = StraightRun(float(run[0]), int(run[1])) if run else StraightRun()

    @property
    def state_mean(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def state_covariance(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def heading_bias_deg(self) -> float:
        """The learned bias in [−180°, 180°) (a PF's particles carry it unwrapped)."""
        return float(wrap_deg(math.degrees(float(self.state_mean[2]))))

    @property
    def step_scale(self) -> float:
        return float(self.state_mean[3])


class FilterpyState(Calibrating):
    """Accessors and the stored form of a self-calibrating filter whose [x, y, b, s] and P live in
    a filterpy filter (``_kf``: the EKF's or the UKF's): both store ``mean``/``cov`` (the position)
    and ``x``/``P`` (the whole state), and load ``x``/``P``."""

    @property
    def _kf(self) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def state_mean(self) -> np.ndarray:
        return np.asarray(self._kf.x, float).reshape(-1).copy()

    @property
    def state_covariance(self) -> np.ndarray:
        return np.asarray(self._kf.P, float).copy()

    @property
    def mean(self) -> np.ndarray:
        return self.state_mean[:2]

    @property
    def covariance(self) -> np.ndarray:
        return self.state_covariance[:2, :2]

    def _set_state(self, x: np.ndarray, P: np.ndarray) -> None:
        x = np.asarray(x, float).reshape(-1)
        self._kf.x = x
        self._kf.P = np.asarray(P, float).reshape(len(x), len(x))

    def _state(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist(),
                "x": self.state_mean.tolist(), "P": self.state_covariance.tolist(), **self._run_state()}

    def _load_state(self, state: dict) -> None:
        self._set_state(np.asarray(state["x"], float), np.asarray(state["P"], float))
        self._load_run(state)
