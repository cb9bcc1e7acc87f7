"""The one interface every tracker has, and the registry that builds them by name.

A tracker estimates a 2-D position ``[x, y]`` (site metres) on one floor. The server
loads it from its stored dict, applies a batch's steps (``predict``) and fixes
(``update``) in time order, and stores ``to_dict()`` back. ``from_dict(to_dict())``
restores a tracker exactly: it gives the same outputs for the same future inputs.

Dict format (JSON-safe, plain lists and numbers)::

    {"filter": "<name>", "version": 2,
     "params": {...constructor keyword arguments...},
     "walls": [[x1, y1, x2, y2], ...],
     "state": {...filter specific: means, covariances, particles, RNG state...}}

Version 1 (before the self-calibrating trackers) named the two-state seed filters
``ekf``, ``ukf``, ``pf`` and ``skpf``; those names now build the augmented filters and the
seed forms are ``ekf-xy``, ``ukf-xy``, ``pf-xy`` and ``skpf-xy``. A version-1 dict loads as
the seed form it was written by (same state, same future outputs), so a stored session
goes on exactly as it started.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from server.estimation.types import Area, Fix, Step

if TYPE_CHECKING:  # (floorplan imports tracking.geometry, and so this package)
    from server.estimation.floorplan import Walkable

FORMAT_VERSION = 2
#: version-1 names of the filters whose seed form has been renamed ``<name>-xy``
RENAMED_IN_V2 = ("ekf", "ukf", "pf", "skpf")

TRACKERS: dict[str, type[Tracker]] = {}


def register(cls: type[Tracker]) -> type[Tracker]:
    """Class decorator: make a tracker constructible by its ``name``."""
    if not getattr(cls, "name", None):
        raise TypeError(f"{cls.__name__} has no name")
    if cls.name in TRACKERS and TRACKERS[cls.name] is not cls:
        raise ValueError(f"tracker name {cls.name!r} already registered")
    TRACKERS[cls.name] = cls
    return cls


def as_walls(walls: Any) -> np.ndarray:
    """Walls as an (n, 4) float array of segments [x1, y1, x2, y2]."""
    if walls is None:
        return np.zeros((0, 4))
    arr = np.asarray(walls, dtype=float)
    if arr.size == 0:
        return np.zeros((0, 4))
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError("walls must be a list of [x1, y1, x2, y2] segments")
    return arr.copy()


def as_mean(mean: Any) -> np.ndarray:
    arr = np.asarray(mean, dtype=float).reshape(-1)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)):
        raise ValueError("mean must be two finite numbers [x, y]")
    return arr.copy()


def symmetric(P: np.ndarray) -> np.ndarray:
    """½(P + Pᵀ): a covariance kept exactly symmetric after arithmetic that rounds each side apart."""
    return 0.5 * (P + P.T)


def _symmetric_2x2(cov: Any, error: str) -> np.ndarray:
    """``cov`` (a 2×2 matrix, or a scalar variance for both axes) as a symmetric float
    array; ``ValueError(error)`` when it is neither or not finite."""
    arr = np.asarray(cov, dtype=float)
    if arr.shape == ():
        arr = np.eye(2) * float(arr)
    if arr.shape != (2, 2) or not np.all(np.isfinite(arr)):
        raise ValueError(error)
    return symmetric(arr)


def as_cov(cov: Any) -> np.ndarray:
    arr = _symmetric_2x2(cov, "covariance must be a 2x2 matrix (or a scalar variance)")
    # 2x2 positive definite ⇔ leading entry and determinant positive (cheaper than eigvalsh).
    if not (arr[0, 0] > 0 and arr[0, 0] * arr[1, 1] - arr[0, 1] * arr[1, 0] > 0):
        raise ValueError("covariance must be positive definite")
    return arr


#: smallest variance (m²) a fix's covariance may have along any axis when used as R
MIN_FIX_VAR_M2 = 0.01
#: largest one (m², σ = 1 km): a fix that wide says nothing along that axis on any site, and wider
#: ones are not harmless: a path-loss fix from transmitters nearly in a line reached 10¹⁷ m² across
#: the line, nearly singular, and P + R was then singular to working precision (the update raised)
MAX_FIX_VAR_M2 = 1.0e6


def fix_cov(cov: Any, min_var: float = MIN_FIX_VAR_M2) -> np.ndarray:
    """A fix's covariance made usable as R: symmetric, eigenvalues within [``min_var``,
    ``MAX_FIX_VAR_M2``].

    Fingerprint models can answer with a singular covariance (all posterior mass on
    one reference point); the floor keeps the update defined instead of raising. The
    ceiling keeps a degenerate one (σ of 10⁸ m along one axis) from doing the same.
    """
    arr = _symmetric_2x2(cov, "fix covariance must be a finite 2x2 matrix")
    if _usable(float(arr[0, 0]), float(arr[0, 1]), float(arr[1, 1]), min_var):
        return arr
    w, v = np.linalg.eigh(arr)
    return (v * np.clip(w, min_var, MAX_FIX_VAR_M2)) @ v.T


def _usable(a: float, b: float, c: float, min_var: float = MIN_FIX_VAR_M2) -> bool:
    """Whether the symmetric 2×2 [[a, b], [b, c]] has both eigenvalues within [``min_var``,
    ``MAX_FIX_VAR_M2``] (closed form: the mean of the diagonal ± half the eigenvalue gap)."""
    half_gap = math.sqrt(0.25 * (a - c) ** 2 + b * b)
    return 0.5 * (a + c) - half_gap >= min_var and 0.5 * (a + c) + half_gap <= MAX_FIX_VAR_M2


def fix_cov_entries(cov) -> tuple[float, float, float]:
    """``fix_cov(cov)`` as Python floats (r00, r01, r11); floats directly in the common case of a
    well-conditioned 2×2 covariance, ``fix_cov`` itself otherwise (floor, ceiling, scalar, errors)."""
    try:
        (c00, c01), (c10, c11) = cov.tolist() if isinstance(cov, np.ndarray) else cov
        a, b, c = float(c00), 0.5 * (float(c01) + float(c10)), float(c11)
    except (TypeError, ValueError):
        a = b = c = math.nan
    if math.isfinite(a) and math.isfinite(b) and math.isfinite(c) and _usable(a, b, c):
        return a, b, c
    R = fix_cov(cov)  # slow path: raises on bad input, bounds a (near-)singular or degenerate covariance
    return float(R[0, 0]), float(R[0, 1]), float(R[1, 1])


@dataclass(frozen=True)
class FixInnovation:
    """What a tracker expects of a fix z with covariance R: the innovation z − E[z], the tracker's
    own part of its covariance (H P Hᵀ), and the share of R that is the fix's own noise (1, or
    1 − ρ for a tracker that carries the walk's fix offset): z ~ N(E[z], H P Hᵀ + noise_share·R)."""

    innovation: np.ndarray
    covariance: np.ndarray
    noise_share: float = 1.0

    def d2(self, R: np.ndarray) -> float:
        """Squared Mahalanobis distance of the fix under its predicted covariance."""
        S = self.covariance + self.noise_share * np.asarray(R, float)
        return float(self.innovation @ np.linalg.solve(S, self.innovation))


class Tracker(ABC):
    """A 2-D position filter fed with PDR steps and position fixes.

    Subclasses set ``name``, implement ``predict``, ``update``, ``mean``,
    ``covariance``, ``reset``, ``_state()`` and ``_load_state()``, and store every
    constructor keyword argument they accept in ``self.params`` (JSON-safe).
    """

    name: ClassVar[str] = ""
    #: whether ``update_range`` does something (otherwise it returns False)
    supports_range: ClassVar[bool] = False
    #: whether the state carries the PDR's heading bias and step scale (``selfcal``)
    augmented: ClassVar[bool] = False

    def __init__(self, initial_mean, initial_cov, walls=None, seed: int | None = None):
        self.walls = as_walls(walls)
        self.seed = seed
        self.params: dict[str, Any] = {}
        #: the floor's walkable area (None: unconstrained); set by the session, not stored
        self.walkable: Walkable | None = None
        #: the floor's grid direction measured from its survey (degrees; None: none), for a floor
        #: whose walls give none; set by the session, not stored (``building_grid``)
        self.survey_grid_deg: float | None = None

    # -- the filter ---------------------------------------------------------------
    @abstractmethod
    def predict(self, step: Step) -> None:
        """Move the estimate by one PDR step."""

    @abstractmethod
    def update(self, fix: Fix) -> None:
        """Correct the estimate with a position fix (fix.covariance is its R)."""

    def fix_innovation(self, fix: Fix) -> FixInnovation:
        """What the tracker expects of ``fix`` (the innovation gate's and the fix-noise learning's
        view): by default z = position + the fix's own noise."""
        return FixInnovation(np.asarray(fix.mean, float) - self.mean, self.covariance)

    def update_range(self, beacon_xy, range_m: float, range_std_m: float, on_wall=None) -> bool:
        """Correct with a range to a beacon; returns whether it was used.

        Trackers that do not support ranges ignore it and return False.
        """
        return False

    @property
    @abstractmethod
    def mean(self) -> np.ndarray:
        """Current position estimate [x, y] (a copy)."""

    @property
    @abstractmethod
    def covariance(self) -> np.ndarray:
        """Current 2x2 position covariance in m² (a copy)."""

    @abstractmethod
    def reset(self, mean, cov) -> None:
        """Restart from a new Gaussian (landmark snap, floor change, re-initialisation)."""

    def inflate(self, factor: float) -> None:
        """Grow the uncertainty: the covariance times ``factor`` (≥ 1), the mean kept.

        The session does this when the innovation gate has refused several fixes in a
        row (the tracker may be overconfident rather than the fixes wrong)."""
        self.reset(self.mean, self.covariance * float(factor))

    def set_walls(self, walls) -> None:
        """Replace the wall segments (e.g. after a floor change)."""
        self.walls = as_walls(walls)

    def set_walkable(self, walkable: Walkable | None) -> None:
        """The floor's walkable area from the next input on (None: none). The PF kills particles
        outside it; for every tracker the session reports its estimates inside it."""
        self.walkable = walkable

    def set_survey_grid(self, deg: float | None) -> None:
        """The floor's grid direction from its survey (None: none) from the next input on; the
        self-calibrating filters take it as a heading reference where the walls give no grid."""
        self.survey_grid_deg = None if deg is None else float(deg)

    @property
    def models_walk_offset(self) -> bool:
        """Whether the tracker itself carries the walk's shared fix error (an opt-in state: the
        EKF's ``walk_offset``, the PF's ``fix_bias_share``); the session then adds no consider
        covariance for it (``shared_error``)."""
        return False

    def search_region(self) -> Area | None:
        """The circle the fingerprint model should restrict its candidate reference points to,
        or None for no restriction."""
        return None

    # -- persistence --------------------------------------------------------------
    @abstractmethod
    def _state(self) -> dict[str, Any]:
        """Filter-specific JSON-safe state."""

    @abstractmethod
    def _load_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``_state``."""

    def to_dict(self, walls: bool = True) -> dict[str, Any]:
        """JSON-safe state; ``walls=False`` leaves the walls out (a session takes them from its
        site before every batch, so they need not be stored with each session)."""
        return {
            "filter": self.name,
            "version": FORMAT_VERSION,
            "params": dict(self.params),
            "walls": self.walls.tolist() if walls else [],
            "state": self._state(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Tracker:
        """Restore a tracker stored by ``to_dict`` (dispatches on ``data["filter"]``)."""
        data = migrate_dict(data)
        name = data.get("filter")
        target = (TRACKERS.get(name) if isinstance(name, str) else None) if cls is Tracker else cls
        if target is None:
            raise ValueError(f"unknown tracker {name!r}")
        if name != target.name:
            raise ValueError(f"dict is for tracker {name!r}, not {target.name!r}")
        if data.get("version") != FORMAT_VERSION:
            raise ValueError(f"unsupported tracker dict version {data.get('version')!r}")
        return target._restore(data["state"], data.get("walls"), data.get("params", {}))

    @classmethod
    def _restore(cls, state: dict[str, Any], walls, params: dict[str, Any]) -> Tracker:
        """A tracker holding ``state`` (a ``_state()``): built from its mean and covariance,
        then loaded. A tracker whose construction draws what loading replaces overrides it."""
        obj = cls(state["mean"], state["cov"], walls=walls, seed=None, **params)
        obj._load_state(state)
        return obj

    def __repr__(self) -> str:
        m = self.mean
        return f"<{type(self).__name__} mean=({m[0]:.2f}, {m[1]:.2f}) trace={np.trace(self.covariance):.3f}>"


def migrate_dict(data: dict[str, Any]) -> dict[str, Any]:
    """A version-1 dict as version 2: the renamed seed filters get their ``-xy`` name."""
    if isinstance(data, dict) and data.get("version") == 1:
        name = data.get("filter")
        data = {**data, "version": FORMAT_VERSION,
                "filter": f"{name}-xy" if name in RENAMED_IN_V2 else name}
    return data


def make_tracker(name: str, initial_mean, initial_cov, walls=None, seed: int | None = None, **params) -> Tracker:
    """Build a tracker by its registered name (``kf``, ``ekf``, ``ukf``, ``pf``, ``skpf``, ``fkf``, and the
    two-state seed forms ``ekf-xy``, ``ukf-xy``, ``pf-xy``, ``skpf-xy``)."""
    try:
        cls = TRACKERS[name]
    except KeyError:
        raise ValueError(f"unknown tracker {name!r}; known: {sorted(TRACKERS)}") from None
    return cls(initial_mean, initial_cov, walls=walls, seed=seed, **params)


def tracker_from_dict(data: dict[str, Any]) -> Tracker:
    """Restore any tracker from its ``to_dict()``."""
    return Tracker.from_dict(data)


def tracker_names() -> list[str]:
    return sorted(TRACKERS)
