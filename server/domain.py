"""The service's domain types: what services, the store and routes pass between them.

Frozen dataclasses, grouped by aggregate. Estimation types (steps, scans, fixes,
estimates) live in ``server.estimation.types``; these are the service's own records.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Literal, Protocol

from server.estimation.types import Estimate, Fix, ScanNote

# --- tracking sessions ---------------------------------------------------------------------

#: most steps, and most scans, in one batch (413 beyond)
MAX_BATCH_STEPS = 1000
MAX_BATCH_SCANS = 1000


@dataclass(frozen=True)
class SessionInfo:
    """A tracking session as a caller sees it; ``owner_key`` is the hash of the key that opened it."""

    id: str
    site_id: int
    owner_key: str
    filter: str
    model_id: int | None
    status: str
    estimate: Estimate | None
    created_at: datetime
    last_seq: int
    track_length: int
    #: the tracker parameters it was opened with, when any (read with one session: a list reads no
    #: tracker state, and leaves them out)
    filter_params: Mapping[str, float] | None = None


@dataclass(frozen=True)
class FeedState:
    """What applying a batch reads: the session's row and its site's revision."""

    site_id: int
    owner_key: str
    model_id: int | None
    status: str
    state: dict[str, Any]
    last_seq: int
    track_length: int
    site_revision: str


@dataclass(frozen=True)
class BatchAnswer:
    """The answer to a batch, stored with it so that a replay gets it again."""

    seq: int
    estimate: Estimate | None
    applied_steps: int
    applied_scans: int
    skipped_scans: tuple[ScanNote, ...] = field(default=())
    rejected_fixes: tuple[ScanNote, ...] = field(default=())
    rejected_snaps: tuple[ScanNote, ...] = field(default=())

    def to_dict(self) -> dict[str, Any]:
        return {
            "seq": self.seq,
            "estimate": None if self.estimate is None else self.estimate.to_dict(),
            "applied_steps": self.applied_steps,
            "applied_scans": self.applied_scans,
            "skipped_scans": _note_dicts(self.skipped_scans),
            "rejected_fixes": _note_dicts(self.rejected_fixes),
            "rejected_snaps": _note_dicts(self.rejected_snaps),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BatchAnswer:
        """Answers stored before the innovation gate have no ``rejected_fixes``, and before the
        snaps' gate no ``rejected_snaps``."""
        return cls(
            seq=d["seq"],
            estimate=None if d["estimate"] is None else Estimate.from_dict(d["estimate"]),
            applied_steps=d["applied_steps"],
            applied_scans=d["applied_scans"],
            skipped_scans=_notes(d, "skipped_scans"),
            rejected_fixes=_notes(d, "rejected_fixes"),
            rejected_snaps=_notes(d, "rejected_snaps"),
        )


@dataclass(frozen=True)
class GateMarks:
    """What the innovation gate refused at one scan estimate of a track (its fingerprint fix, its
    landmark snap or both), read off the stored answer of the batch that made it."""

    fix_refused: bool = False
    snap_refused: bool = False

    def __or__(self, other: GateMarks) -> GateMarks:
        return GateMarks(self.fix_refused or other.fix_refused, self.snap_refused or other.snap_refused)

    def fields(self) -> dict[str, bool]:
        """The track's extension fields for these marks: each present (true) only when set."""
        return {name: True for name, on in (("fix_refused", self.fix_refused), ("snap_refused", self.snap_refused))
                if on}


#: an answer's notes that mark a scan estimate, and the mark each sets
GATE_NOTES = {"rejected_fixes": GateMarks(fix_refused=True), "rejected_snaps": GateMarks(snap_refused=True)}


def _note_dicts(notes: tuple[ScanNote, ...]) -> list[dict[str, Any]]:
    """The stored form; ``applied`` only where known (the API's answer leaves it out)."""
    return [{"index": n.index, "reason": n.reason, **({} if n.applied is None else {"applied": n.applied})}
            for n in notes]


def _notes(d: dict[str, Any], key: str) -> tuple[ScanNote, ...]:
    """The notes stored under ``key`` (none in an answer stored before that key existed; no
    ``applied`` in one stored before it was kept)."""
    return tuple(ScanNote(n["index"], n["reason"], n.get("applied")) for n in d.get(key, []))


# --- API keys ---------------------------------------------------------------------------------

Scope = Literal["admin", "device"]


@dataclass(frozen=True)
class ApiKeyInfo:
    """A key created from the CLI; only its SHA-256 is known, never the key."""

    id: int
    name: str
    scope: Scope
    key_hash: str
    created_at: datetime
    revoked_at: datetime | None = None


# --- sites ------------------------------------------------------------------------------------

#: a wall segment (x1, y1, x2, y2), metres
Wall = tuple[float, float, float, float]
#: a walkable area: the exterior ring of a polygon, [(x, y), ...] in site metres
Polygon = tuple[tuple[float, float], ...]
#: a floor's identity on its site: (building, level)
FloorId = tuple[int, int]


@dataclass(frozen=True)
class Floor:
    """A floor: ``level`` of ``building`` (0 on a site of one building)."""

    level: int
    name: str | None = None
    width_m: float | None = None
    height_m: float | None = None
    walls: tuple[Wall, ...] = ()
    building: int = 0
    #: where one can walk, when a plan says so (None: unknown)
    walkable: tuple[Polygon, ...] | None = None

    @property
    def id(self) -> FloorId:
        return (self.building, self.level)


@dataclass(frozen=True)
class Transmitter:
    """A WiFi AP or BLE beacon of a site; position and radio parameters are optional; ``building``
    is set exactly when ``floor`` is (0 when a floor is given without one)."""

    id: str
    kind: str
    floor: int | None = None
    x: float | None = None
    y: float | None = None
    tx_power_dbm: float | None = None
    path_loss_exponent: float | None = None
    building: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "building", None if self.floor is None else (self.building or 0))


class _OnFloor(Protocol):
    @property
    def id(self) -> str: ...
    @property
    def floor(self) -> int | None: ...
    @property
    def building(self) -> int | None: ...


def floor_names(floors: Iterable[FloorId]) -> str:
    """Floors as messages name them: levels alone on a site of one building, else building/level pairs."""
    floors = sorted(floors)
    if all(b == 0 for b, _ in floors):
        return str([level for _, level in floors])
    return "[" + ", ".join(f"building {b} level {level}" for b, level in floors) + "]"


def undeclared_floors(declared: set[FloorId], transmitters: Iterable[_OnFloor]) -> str | None:
    """A site that declares floors accepts transmitters on those (building, level) floors only; None when
    all are fine."""
    if not declared:
        return None
    bad = [t.id for t in transmitters if t.floor is not None and (t.building or 0, t.floor) not in declared]
    return f"transmitter(s) {', '.join(bad[:10])} on a floor the site does not declare {floor_names(declared)}" \
        if bad else None


@dataclass(frozen=True)
class NewSite:
    name: str
    floors: tuple[Floor, ...] = ()
    transmitters: tuple[Transmitter, ...] = ()


@dataclass(frozen=True)
class Site:
    id: int
    name: str
    settings: Mapping[str, Any]
    floors: tuple[Floor, ...]
    created_at: datetime
    #: renewed whenever something a fix depends on changes (see ``server.tables.Site``)
    revision: str


@dataclass(frozen=True)
class SiteCounts:
    transmitters: int = 0
    reference_points: int = 0
    survey_fingerprints: int = 0
    crowd_fingerprints: int = 0


@dataclass(frozen=True)
class SiteSummary:
    """A site with how much it holds, as the site routes show it."""

    site: Site
    counts: SiteCounts


@dataclass(frozen=True)
class SiteContextRecord:
    """What a fix on the site depends on (but the serving model), valid while ``revision`` holds."""

    revision: str
    settings: Mapping[str, Any]
    walls: Mapping[FloorId, tuple[Wall, ...]]
    #: the transmitters with a known position
    transmitters: tuple[Transmitter, ...]


# --- surveys ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class FingerprintRecord:
    """One validated survey scan at a known position; ``label`` names its reference point."""

    x: float
    y: float
    floor: int
    rss: Mapping[str, float]
    heading_deg: float | None = None
    t: float | None = None
    device: str | None = None
    label: str | None = None
    building: int = 0


@dataclass(frozen=True)
class SurveyOutcome:
    accepted: int
    reference_points: int
    new_reference_points: int
    skipped: int = 0
    dry_run: bool = False
    #: the answer stored for an earlier upload with the same idempotency key
    replayed: bool = False
    #: rows of the request that an earlier request of the same ``source`` file had stored
    already_stored: int = 0


@dataclass(frozen=True)
class ReferencePointSummary:
    label: str | None
    floor: int
    x: float
    y: float
    fingerprints: int
    building: int = 0


@dataclass(frozen=True)
class CoverageCell:
    """One transmitter's measured RSS at one reference point (``reference_point_id`` None: the floor's crowd
    fingerprints, which belong to no reference point)."""

    reference_point_id: int | None
    label: str | None
    x: float | None
    y: float | None
    source: str
    fingerprints: int
    heard: int
    mean_rss_dbm: float | None


# --- models -----------------------------------------------------------------------------------

ModelStatus = Literal["queued", "training", "ready", "failed"]
#: when a trained model becomes the site's active one: ``if_none`` (the first ready model of a
#: site), ``if_better`` (also when its held-out mean error is no worse than the active model's),
#: ``always``, ``never``
Activation = Literal["if_none", "if_better", "always", "never"]
ACTIVATIONS: tuple[Activation, ...] = ("if_none", "if_better", "always", "never")


@dataclass(frozen=True)
class ModelSpec:
    """What to train; empty ``kinds`` means every kind of transmitter."""

    algorithm: str
    params: Mapping[str, Any]
    use_heading: bool = False
    kinds: tuple[str, ...] = ()
    include_crowd: bool = True
    activate: Activation = "if_none"


@dataclass(frozen=True)
class ModelInfo:
    id: int
    site_id: int
    algorithm: str
    params: Mapping[str, Any]
    use_heading: bool
    kinds: tuple[str, ...]
    include_crowd: bool
    status: ModelStatus
    error: str | None
    active: bool
    trained_on: int
    metrics: Mapping[str, Any] | None
    created_at: datetime
    updated_at: datetime
    activate: Activation = "if_none"

    @property
    def spec(self) -> ModelSpec:
        return ModelSpec(self.algorithm, self.params, self.use_heading, self.kinds, self.include_crowd, self.activate)


@dataclass(frozen=True)
class ServingModel:
    """A ready model with its artifact's SHA-256 (the model cache's key)."""

    model_id: int
    algorithm: str
    sha256: str


@dataclass(frozen=True)
class ServingCandidate:
    """The model asked to serve (chosen, or the site's active one), ready or not."""

    model_id: int
    algorithm: str
    status: ModelStatus
    sha256: str | None

    def ready(self) -> ServingModel | None:
        """The model as it serves, when it can: trained and with an artifact."""
        if self.status != "ready" or self.sha256 is None:
            return None
        return ServingModel(self.model_id, self.algorithm, self.sha256)


@dataclass(frozen=True)
class Artifact:
    """A trained model, serialised, with the SHA-256 it was stored with."""

    model_id: int
    sha256: str
    blob: bytes


# --- positioning ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Coverage:
    """Whether a scan resembles what was surveyed (``WKNNModel.coverage``): ``ratio`` is its
    distance to the nearest surveyed fingerprint over the model's threshold (the distance 99 %
    of held-out scans at unsurveyed reference points stayed within); above 1 it is out of coverage."""

    ratio: float

    @property
    def inside(self) -> bool:
        return self.ratio <= 1.0


@dataclass(frozen=True)
class Located:
    fix: Fix
    model_id: int
    algorithm: str
    #: None: the model cannot tell
    coverage: Coverage | None = None
