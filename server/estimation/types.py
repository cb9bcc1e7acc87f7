"""The vocabulary shared by fingerprint models and trackers.

Site frame: metres, x east, y north. ``heading_deg`` is clockwise from +y, so a step
of length d along heading h moves by (d·sin h, d·cos h). RSS is dBm in [-130, 0];
a transmitter not heard is absent from a scan (in arrays: NaN). A floor is a (building,
level) pair: ``building`` is 0 on a site of one building.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def step_displacement(length_m: float, heading_deg: float) -> np.ndarray:
    """The (dx, dy) of one step in the site frame."""
    h = math.radians(heading_deg)
    return np.array([length_m * math.sin(h), length_m * math.cos(h)])


@dataclass(frozen=True)
class Step:
    """One PDR step as the phone reports it.

    The std defaults, used when a phone sends none, are the white part of the PDR's
    error measured on real walks (``benchmarks/pdr_noise.py`` on the shared MSFT walks:
    in-walk step length spread 0.17 m, heading 2.9–3.5° about its slowly varying bias);
    the bias itself is the self-calibrating trackers' business (``tracking/selfcal.py``)."""

    t: float
    length_m: float
    heading_deg: float
    length_std_m: float = 0.15
    heading_std_deg: float = 5.0


@dataclass(frozen=True)
class InitialHeading:
    """The walker's direction at a session's start (degrees, site frame) as a phone knows it
    independently of its own compass (a known entrance, a user's tap), and that knowledge's σ."""

    heading_deg: float
    std_deg: float


@dataclass(frozen=True)
class Scan:
    """One RSS scan: transmitter id → dBm."""

    t: float
    rss: dict[str, float]
    heading_deg: float | None = None


@dataclass(frozen=True)
class Candidate:
    """A reference point with its posterior probability."""

    label: str
    x: float
    y: float
    floor: int
    probability: float
    building: int = 0


@dataclass(frozen=True)
class Fix:
    """A position estimate from one scan: mean, 2×2 covariance (m²), floor and its building.
    ``shared_share``: the share of ``covariance`` that a walk's fixes have in common — the map's
    measured ``walk_share`` (an EKF with ``walk_offset`` estimates the walk's offset with it), None for a
    fingerprint fix whose map did not measure it (only a PF with ``fix_bias_share`` models it),
    0 for a fix whose error is its own (a landmark snap)."""

    x: float
    y: float
    floor: int
    covariance: np.ndarray
    reference_point: str | None = None
    candidates: list[Candidate] = field(default_factory=list)
    building: int = 0
    shared_share: float | None = None

    @property
    def mean(self) -> np.ndarray:
        return np.array([self.x, self.y])


Covariance2 = tuple[tuple[float, float], tuple[float, float]]


@dataclass(frozen=True)
class Estimate:
    """One point of a session's track: where the tracker is after an input.

    ``source`` is ``init`` (the session's given start), ``step`` or ``scan``; ``t`` is None
    only for an initial position given before the session's first input."""

    t: float | None
    x: float
    y: float
    floor: int
    covariance: Covariance2
    source: str
    building: int = 0

    @classmethod
    def of(cls, t: float | None, mean, cov, floor: int, source: str, building: int = 0) -> Estimate:
        c = np.asarray(cov, float)
        return cls(
            t=None if t is None else float(t), x=float(mean[0]), y=float(mean[1]), floor=int(floor),
            covariance=((float(c[0, 0]), float(c[0, 1])), (float(c[1, 0]), float(c[1, 1]))), source=source,
            building=int(building),
        )

    def to_dict(self) -> dict:
        """The JSON form (also the API's ``Estimate``)."""
        return {"t": self.t, "x": self.x, "y": self.y, "floor": self.floor, "building": self.building,
                "covariance": [list(self.covariance[0]), list(self.covariance[1])], "source": self.source}

    @classmethod
    def from_dict(cls, d: dict) -> Estimate:
        """Estimates stored before buildings have none: building 0."""
        (a, b), (c, e) = d["covariance"]
        return cls(d["t"], d["x"], d["y"], d["floor"], ((a, b), (c, e)), d["source"], d.get("building", 0))


@dataclass(frozen=True)
class StepJoint:
    """A particle filter's step as its cloud saw it: the joint moments of each particle's state
    before the step (its ancestor's [x, y, b, s]) and after it, under the weights after it (walls
    that killed particles and the grid's reweighing weigh the ancestors too). The smoother's gain
    for the step is then the cloud's own regression of the old state on the new (an ensemble RTS),
    not a linearised model's that knows nothing of the walls."""

    #: the ancestors' mean and covariance under the weights after the step
    origin_mean: tuple[float, ...]
    origin_covariance: tuple[tuple[float, ...], ...]
    #: E[(old − origin_mean)(new − new mean)ᵀ]
    cross: tuple[tuple[float, ...], ...]

    @classmethod
    def of(cls, origin_mean, joint_cov) -> StepJoint:
        """From the ancestors' mean and the 2n × 2n covariance of the pairs [ancestor, particle]."""
        M = np.asarray(joint_cov, float)
        n = len(origin_mean)
        return cls(tuple(np.asarray(origin_mean, float).tolist()), _matrix(0.5 * (M[:n, :n] + M[:n, :n].T)),
                   _matrix(M[:n, n:]))

    def to_dict(self) -> dict[str, Any]:
        """The stored form: the origin covariance's upper triangle and the cross-covariance row by row."""
        return {"m": list(self.origin_mean), "P": _upper(self.origin_covariance),
                "X": [v for row in self.cross for v in row]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StepJoint:
        n = len(d["m"])
        X = np.array(d["X"], float).reshape(n, n)
        return cls(tuple(float(v) for v in d["m"]), _matrix(_from_upper(d["P"], n)), _matrix(X))


def _matrix(a) -> tuple[tuple[float, ...], ...]:
    return tuple(map(tuple, np.asarray(a, float).tolist()))


def _upper(m: tuple[tuple[float, ...], ...]) -> list[float]:
    """A symmetric matrix's upper triangle, row by row."""
    return [m[i][j] for i in range(len(m)) for j in range(i, len(m))]


def _from_upper(values, n: int) -> np.ndarray:
    upper = iter(values)
    P = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            P[i, j] = P[j, i] = float(next(upper))
    return P


@dataclass(frozen=True)
class FullState:
    """A self-calibrating tracker's whole state at one track estimate, kept for the smoother:
    the mean [x, y, b, s], its 4 × 4 covariance, and for a step estimate the step (length m,
    heading °) that predicted it (``tracking.smoother``: an RTS over the whole state bends the
    path before a heading bias was learned as that bias, not as independent noise per step) and,
    from a particle filter, the step's joint moments (``StepJoint``)."""

    mean: tuple[float, ...]
    covariance: tuple[tuple[float, ...], ...]
    step: tuple[float, float] | None = None
    joint: StepJoint | None = None

    @classmethod
    def of(cls, mean, cov, step: Step | None = None, joint: StepJoint | None = None) -> FullState:
        """Symmetric (a sample covariance may not be to the last bit): stored as its upper triangle."""
        c = np.asarray(cov, float)
        return cls(tuple(np.asarray(mean, float).tolist()), _matrix(0.5 * (c + c.T)),
                   None if step is None else (float(step.length_m), float(step.heading_deg)), joint)

    def to_dict(self) -> dict[str, Any]:
        """The stored form: the covariance's upper triangle, row by row."""
        out: dict[str, Any] = {"m": list(self.mean), "P": _upper(self.covariance)}
        if self.step is not None:
            out["u"] = list(self.step)
        if self.joint is not None:
            out["j"] = self.joint.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FullState:
        u, j = d.get("u"), d.get("j")
        return cls(tuple(float(v) for v in d["m"]), _matrix(_from_upper(d["P"], len(d["m"]))),
                   None if u is None else (float(u[0]), float(u[1])), None if j is None else StepJoint.from_dict(j))


@dataclass(frozen=True)
class Beacon:
    """A transmitter with a known position; radio parameters make ranges possible. A beacon
    without a floor is heard on every floor of every building."""

    id: str
    x: float
    y: float
    floor: int | None
    tx_power_dbm: float | None = None
    path_loss_exponent: float | None = None
    building: int | None = None

    def on(self, building: int, floor: int) -> bool:
        """Whether the beacon serves that floor of that building."""
        return self.floor is None or (self.floor == floor and (self.building or 0) == building)


@dataclass(frozen=True)
class SiteMap:
    """What a tracker knows of a site: positioned transmitters by id; walls, walkable area and the
    survey's grid direction by (building, level)."""

    beacons: dict[str, Beacon] = field(default_factory=dict)
    walls: dict[tuple[int, int], list] = field(default_factory=dict)
    #: walkable area by (building, level), a ``floorplan.Walkable``; a floor without one is unconstrained
    walkable: dict[tuple[int, int], Any] = field(default_factory=dict)
    #: grid direction (degrees, mod 90°) by (building, level) measured from the survey
    #: (``building_grid.survey_grids``); used where the floor's walls give none
    grids: dict[tuple[int, int], float] = field(default_factory=dict)

    def walls_of(self, level: int, building: int = 0) -> list:
        return self.walls.get((building, level), [])


@dataclass(frozen=True)
class Area:
    """A circle to which a fingerprint model may restrict its candidates."""

    x: float
    y: float
    radius_m: float


@dataclass(frozen=True)
class CrowdPoint:
    """A crowdsourced fingerprint: a confident estimate's position with the scan's RSS.

    ``counts`` says how many readings each transmitter's mean ``rss`` holds; ``count`` how
    many points were merged into this one."""

    x: float
    y: float
    floor: int
    rss: dict[str, float]
    count: int = 1
    counts: dict[str, int] | None = None
    building: int = 0

    def tx_counts(self) -> dict[str, int]:
        return self.counts if self.counts is not None else dict.fromkeys(self.rss, self.count)


@dataclass(frozen=True)
class ScanNote:
    """Why the scan at ``index`` of its batch gave no fix (skipped) or had its fix or snap refused;
    ``applied``: which of the batch's applied scans it was (0-based, in the time order they were
    applied, so the batch's ``applied``-th scan estimate is its), None for a skipped scan."""

    index: int
    reason: str
    applied: int | None = None


@dataclass(frozen=True)
class CrowdCandidate:
    """A crowd fingerprint a batch proposes, with the scan it comes from."""

    point: CrowdPoint
    scan: Scan


@dataclass(frozen=True)
class ScanResult:
    """What one applied scan did: the estimate after it and, where the innovation gate refused
    them, why it refused the scan's fingerprint fix and its landmark snap (None: not refused)."""

    estimate: Estimate
    refused_fix: str | None = None
    refused_snap: str | None = None


@dataclass(frozen=True)
class BatchOutcome:
    """What one batch did to a session: the new track estimates (in time order), the
    estimate after it, how many steps and scans moved the tracker, scans without a fix,
    fixes and landmark snaps the innovation gate refused, and crowd fingerprints to store."""

    estimates: tuple[Estimate, ...]
    estimate: Estimate | None
    applied_steps: int
    applied_scans: int
    skipped_scans: tuple[ScanNote, ...]
    rejected_fixes: tuple[ScanNote, ...]
    crowd: tuple[CrowdCandidate, ...]
    #: the time the initial estimate (given without one) took from this batch's first input
    init_t: float | None = None
    #: per estimate, a self-calibrating tracker's whole state (``FullState``; None for the others)
    states: tuple[FullState | None, ...] = ()
    rejected_snaps: tuple[ScanNote, ...] = ()


@dataclass(frozen=True)
class LateInput:
    """A step or scan dated before the session's last applied input."""

    kind: str  # "step" or "scan"
    index: int
    t: float


class LateInputs(ValueError):
    """A batch holds inputs older than what the session already applied; nothing was applied."""

    def __init__(self, items: list[LateInput], last_t: float):
        super().__init__(f"{len(items)} inputs before the last applied time {last_t}")
        self.items = items
        self.last_t = last_t


class TrackerFailure(Exception):
    """The tracker could not apply a batch's inputs, or the smoother its stored track: a numerical
    failure (a covariance no longer positive definite, a singular innovation covariance). The
    estimator is then in an undefined state and must be dropped; ``str(exc)`` says what failed and how."""


class NoFix(Exception):
    """A scan gives no fix (no model, no known transmitter...); ``str(exc)`` says why."""
