"""Request and response bodies of the HTTP API (API.md), with every edge rule enforced here."""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    StringConstraints,
    field_validator,
    model_validator,
)

from server.domain import Activation, undeclared_floors
from server.estimation.fingerprint.registry import ALGORITHMS
from server.estimation.tracking import tracker_names
from server.estimation.tracking.tuning import params_doc

#: ``wifi:<bssid>`` / ``ble:<uuid>:<major>:<minor>``, or a data set's name for a transmitter.
TX_ID_PATTERN = (
    r"^(?:wifi:(?:[0-9a-f]{2}(?::[0-9a-f]{2}){5}|[a-z0-9._-]{1,64})"
    r"|ble:(?:[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}:\d{1,5}:\d{1,5}"
    r"|[a-z0-9._-]{1,64}))$"
)
RSS_MIN_DBM, RSS_MAX_DBM = -130.0, 0.0

TxId = Annotated[str, StringConstraints(pattern=TX_ID_PATTERN), Field(
    description="Transmitter id: `wifi:<bssid, lower case>` or `ble:<uuid, lower case>:<major>:<minor>`; "
    "where a data set names its transmitters, `wifi:<name>` / `ble:<name>` with the name in `[a-z0-9._-]`."
)]
Dbm = Annotated[float, Field(ge=RSS_MIN_DBM, le=RSS_MAX_DBM, allow_inf_nan=False,
                             description="Received signal strength in dBm, [-130, 0].")]
Metres = Annotated[float, Field(allow_inf_nan=False, ge=-1e7, le=1e7)]
Seconds = Annotated[float, Field(allow_inf_nan=False, ge=-1e12, le=1e12,
                                 description="Time in seconds (float, any epoch, monotonic within one session), "
                                 "|t| ≤ 1e12.")]
#: a stored row's id: the range every backend's integer column holds (PostgreSQL's is 32-bit)
DbId = Annotated[int, Field(ge=-(2**31), le=2**31 - 1)]
#: text the database can store: no NUL character (PostgreSQL refuses it)
NO_NUL = r"^[^\x00]*$"
Degrees = Annotated[float, Field(allow_inf_nan=False, ge=-360, le=360, description=(
    "Heading in degrees clockwise from the site's +y axis (0 = +y/north, 90 = +x/east): "
    "a step of length d moves by (d·sin h, d·cos h)."))]
Level = Annotated[int, Field(ge=-20, le=200, description="Floor level, an integer (0 = ground).")]
#: buildings are numbered 0, 1, ...; a site of one building has only building 0
MAX_BUILDING = 999
BUILDING_DOC = ("Extension: the building the floor belongs to, an integer in [0, 999] (default 0: a site of one "
                "building). A floor is a (building, level) pair (docs/api-conventions.md).")


def _not_bool(value: Any) -> Any:
    if isinstance(value, bool):
        raise ValueError("building must be an integer, not a boolean")
    return value


BuildingNumber = Annotated[int, BeforeValidator(_not_bool), Field(ge=0, le=MAX_BUILDING)]
Building = Annotated[BuildingNumber, Field(description=BUILDING_DOC)]
#: where a field is a position in the site frame
X_DOC = "Metres east in the site frame (x axis; origin chosen by the site)."
Y_DOC = "Metres north in the site frame (y axis)."
COV_DOC = "2×2 row-major covariance [[sxx, sxy], [sxy, syy]] of (x, y), in m²."

#: the names a session's ``filter`` and a model's ``algorithm`` may take, published as enums in the schema
FILTERS: list[str] = list(tracker_names())
ALGORITHM_NAMES: list[str] = sorted(ALGORITHMS)
_FILTER_ENUM: dict[str, Any] = {"enum": FILTERS}
_ALGORITHM_ENUM: dict[str, Any] = {"enum": ALGORITHM_NAMES}
Name = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=200, pattern=NO_NUL)]


def _non_empty(rss: dict[str, float]) -> dict[str, float]:
    if not rss:
        raise ValueError("scan is empty: at least one transmitter must be heard")
    return rss


#: One scan: transmitter id → dBm, at least one entry.
Rss = Annotated[dict[TxId, Dbm], AfterValidator(_non_empty)]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# --- sites ---------------------------------------------------------------------------


#: most points of all a floor's walkable polygons together
MAX_WALKABLE_POINTS = 100_000
Ring = Annotated[list[tuple[Metres, Metres]], Field(min_length=3, max_length=MAX_WALKABLE_POINTS)]


def _walkable_size(polygons: list[list[tuple[float, float]]] | None) -> list[list[tuple[float, float]]] | None:
    if polygons is not None and sum(len(p) for p in polygons) > MAX_WALKABLE_POINTS:
        raise ValueError(f"walkable polygons hold more than {MAX_WALKABLE_POINTS} points together")
    return polygons


Walkable = Annotated[list[Ring], Field(max_length=10_000), AfterValidator(_walkable_size)]
WALKABLE_DOC = ("Extension: where one can walk on the floor, as polygons in site metres, each the exterior ring "
                "[[x, y], ...] of at least 3 points (at most 100,000 points in all); null or absent: unknown. "
                "Tracking estimates on the floor lie inside it (the walkable point nearest the tracker's mean).")


class FloorIn(Strict):
    level: Level
    building: Building = 0
    name: Name | None = None
    width_m: Annotated[float, Field(gt=0, le=1e5)] | None = None
    height_m: Annotated[float, Field(gt=0, le=1e5)] | None = None
    walls: Annotated[list[tuple[Metres, Metres, Metres, Metres]], Field(
        max_length=100_000, description="Wall segments [x1, y1, x2, y2] in site metres.")] = []
    walkable: Walkable | None = Field(None, description=WALKABLE_DOC)


class TransmitterIn(Strict):
    id: TxId
    kind: Literal["wifi", "ble"] = Field(description="`wifi` (access point) or `ble` (iBeacon); the id's prefix.")
    floor: Level | None = None
    building: BuildingNumber | None = Field(
        None, description="Extension: the building of `floor` (default 0 when a floor is given; only with a floor).")
    x: Metres | None = Field(None, description=X_DOC)
    y: Metres | None = Field(None, description=Y_DOC)
    tx_power_dbm: Annotated[float, Field(ge=-130, le=30)] | None = None
    path_loss_exponent: Annotated[float, Field(gt=0, le=10)] | None = None

    @model_validator(mode="after")
    def _consistent(self) -> TransmitterIn:
        if not self.id.startswith(self.kind + ":"):
            raise ValueError(f"id {self.id!r} does not match kind {self.kind!r}")
        if (self.x is None) != (self.y is None):
            raise ValueError("give both x and y, or neither")
        if self.building is not None and self.floor is None:
            raise ValueError("a building is given only with a floor")
        return self


TransmitterList = Annotated[list[TransmitterIn], Field(max_length=100_000)]


class SiteIn(Strict):
    name: Name
    floors: Annotated[list[FloorIn], Field(max_length=1000)] = []
    transmitters: TransmitterList = []

    @model_validator(mode="after")
    def _unique(self) -> SiteIn:
        floors = [(f.building, f.level) for f in self.floors]
        if len(floors) != len(set(floors)):
            raise ValueError("floor levels must be unique within a building")
        ids = [t.id for t in self.transmitters]
        if len(ids) != len(set(ids)):
            raise ValueError("transmitter ids must be unique")
        undeclared = undeclared_floors(set(floors), self.transmitters)
        if undeclared:
            raise ValueError(undeclared)
        return self


class FloorOut(BaseModel):
    level: int
    building: int = Field(0, description=BUILDING_DOC)
    name: str | None
    width_m: float | None
    height_m: float | None
    walls: list[list[float]]
    walkable: list[list[list[float]]] | None = Field(None, description=WALKABLE_DOC)


class TransmitterOut(BaseModel):
    id: str
    kind: str
    floor: int | None
    building: int | None = Field(None, description="Extension: the building of `floor` (null when no floor).")
    x: float | None
    y: float | None
    tx_power_dbm: float | None
    path_loss_exponent: float | None


class FingerprintCounts(BaseModel):
    survey: int
    crowd: int


class SiteSettings(Strict):
    crowdsourcing: bool | None = Field(
        None, description="Confident tracking-session estimates with their scans become crowd fingerprints."
    )


class SitePatch(Strict):
    settings: SiteSettings


class SiteOut(BaseModel):
    id: int
    name: str
    settings: dict = Field({}, description="Site settings, e.g. {\"crowdsourcing\": true}.")
    floors: list[FloorOut]
    transmitters: int
    reference_points: int
    fingerprints: FingerprintCounts
    created_at: datetime


class ReferencePointOut(BaseModel):
    label: str | None
    floor: int
    building: int = Field(0, description=BUILDING_DOC)
    x: float
    y: float
    fingerprints: int


class CoverageCount(BaseModel):
    fingerprints: int = Field(description="Fingerprints counted.")
    heard: int = Field(description="How many of them heard the transmitter.")
    mean_rss_dbm: float | None = Field(description="Mean RSS (dBm) over the fingerprints that heard it; "
                                       "null when none did.")


class CoveragePointOut(CoverageCount):
    label: str | None
    x: float = Field(description=X_DOC)
    y: float = Field(description=Y_DOC)


class CoverageOut(BaseModel):
    transmitter: str
    floor: int
    building: int = Field(0, description=BUILDING_DOC)
    reference_points: list[CoveragePointOut] = Field(
        description="Every reference point of the floor with its survey fingerprints."
    )
    crowd: CoverageCount = Field(
        description="The floor's crowd fingerprints (they belong to no reference point), all together."
    )


# --- surveys ---------------------------------------------------------------------------


class FingerprintIn(Strict):
    x: Metres = Field(description=X_DOC)
    y: Metres = Field(description=Y_DOC)
    floor: Level
    building: Building = 0
    rss: Rss = Field(description="Transmitter id → dBm; a transmitter not heard is absent (never a sentinel).")
    heading_deg: Degrees | None = None
    t: Seconds | None = None
    device: Annotated[str, StringConstraints(max_length=200, pattern=NO_NUL)] | None = None
    label: Annotated[str, StringConstraints(min_length=1, max_length=200, pattern=NO_NUL)] | None = None


class SurveyIn(Strict):
    fingerprints: list[FingerprintIn]


class SurveyResult(BaseModel):
    accepted: int = Field(description="Fingerprints stored (or, on a dry run, that would be).")
    reference_points: int = Field(description="Distinct reference points the upload touched.")
    new_reference_points: int = Field(description="Reference points the upload created.")
    skipped: int = Field(0, description="Rows that heard nothing (UJIIndoorLoc format only).")
    already_stored: int = Field(0, description="Rows an earlier upload of the same `source` file had stored (not stored again).")
    dry_run: bool = False


# --- tracking sessions -------------------------------------------------------------

Cov2 = tuple[tuple[Metres, Metres], tuple[Metres, Metres]]


def _positive_definite(cov: Cov2 | None) -> Cov2 | None:
    if cov is None:
        return cov
    (a, b), (c, d) = cov
    if abs(b - c) > 1e-9 * max(1.0, abs(b), abs(c)):
        raise ValueError("covariance must be symmetric")
    if not (a > 0 and a * d - b * c > 0):
        raise ValueError("covariance must be positive definite")
    return cov


class InitialIn(Strict):
    x: Metres = Field(description=X_DOC)
    y: Metres = Field(description=Y_DOC)
    floor: Level
    building: Building = 0
    heading_deg: Degrees | None = Field(
        None, description="The walker's direction at the start (degrees clockwise from +y, as a step's). Alone it "
        "is taken as the phone's own reading (the compass its steps use), which tells the tracker nothing it does "
        "not have, and is not used; with `heading_std_deg` see there.")
    heading_std_deg: Annotated[float, Field(gt=0, le=180, allow_inf_nan=False)] | None = Field(
        None, description="Extension. σ (degrees) of `heading_deg` known independently of the phone's compass "
        "(a known entrance, a user's tap): a self-calibrating tracker (`ekf`, `ukf`, `skpf`, `pf`) then takes "
        "the difference between `heading_deg` and its first step's heading as an observation of the phone's "
        "heading bias (variance this σ² plus that step's `heading_std_deg`²). The seed forms, `kf` and `fkf` "
        "carry no bias and ignore it. Needs `heading_deg`.")

    @model_validator(mode="after")
    def _heading_std_needs_heading(self) -> InitialIn:
        if self.heading_std_deg is not None and self.heading_deg is None:
            raise ValueError("initial.heading_std_deg needs initial.heading_deg")
        return self
    covariance: Annotated[Cov2, AfterValidator(_positive_definite)] | None = Field(
        None, description=COV_DOC + " Symmetric, positive definite; default: the tracker's own.")


class SessionIn(Strict):
    site_id: DbId
    filter: str = Field(description="The tracker to run: `ekf`, `ukf`, `pf`, `skpf` (self-calibrating: they "
                        "learn a heading bias and a step-length scale from the fixes), their seed forms `ekf-xy`, "
                        "`ukf-xy`, `pf-xy`, `skpf-xy` (position only), or the linear two-state `kf` and `fkf` "
                        "(see docs/api-conventions.md).",
                        json_schema_extra=_FILTER_ENUM)
    model_id: DbId | None = None
    initial: InitialIn | None = None
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] | None = Field(
        None, description="Extension. The tracker's random seed (a particle filter's draws): the same seed, "
        "model and batches give the same track, for replays and for comparing settings on the same draws. "
        "Default: derived from the session id.")
    filter_params: Annotated[dict[Annotated[str, StringConstraints(max_length=64)], StrictInt | StrictFloat],
                             Field(max_length=32)] | None = Field(
        None, description="Extension. Numbers that override the tracker's defaults, by name; an unknown name, a "
        "value out of range or a fraction where a count is meant is a 422 naming it. The session keeps them "
        "(`GET /api/v1/sessions/{id}` echoes them). Per filter, with ranges and defaults: " + params_doc() + ".")

    @field_validator("filter")
    @classmethod
    def _known_filter(cls, value: str) -> str:
        from server.estimation.tracking import tracker_names

        if value not in tracker_names():
            raise ValueError(f"filter {value!r} is not one of {tracker_names()}")
        return value


class StepIn(Strict):
    t: Seconds
    length_m: Annotated[float, Field(ge=0, le=5, allow_inf_nan=False, description="Step length in metres.")]
    heading_deg: Degrees
    length_std_m: Annotated[float, Field(gt=0, le=5, allow_inf_nan=False)] | None = None
    heading_std_deg: Annotated[float, Field(gt=0, le=180, allow_inf_nan=False)] | None = None


class ScanIn(Strict):
    t: Seconds
    rss: Rss
    heading_deg: Degrees | None = None


class BatchIn(Strict):
    seq: Annotated[int, Field(ge=0, le=2**31 - 1)]
    steps: list[StepIn] = []
    scans: list[ScanIn] = []


class EstimateOut(BaseModel):
    t: float | None = Field(description="Seconds, the time of the input that made it (null: an initial "
                            "position before any input).")
    x: float = Field(description=X_DOC)
    y: float = Field(description=Y_DOC)
    floor: int
    building: int = Field(0, description=BUILDING_DOC)
    covariance: list[list[float]] = Field(description=COV_DOC + (
        " For ekf/ukf/skpf/pf sessions it also counts the error a walk's fixes share (the model's "
        "`metrics.calibration.walk_share`) and a cold start's narrowed inputs, which the tracker's own "
        "covariance leaves out."))
    source: Literal["step", "scan", "init"] = Field(
        description="What made it: a PDR step, a scan's fix, or the session's initial position.")


class TrackEstimateOut(EstimateOut):
    fix_refused: bool | None = Field(
        None, description="Extension, present (true) only on a `scan` estimate whose fingerprint fix the "
        "innovation gate refused (the batch's `rejected_fixes`); absent otherwise.")
    snap_refused: bool | None = Field(
        None, description="Extension, present (true) only on a `scan` estimate whose landmark snap the "
        "innovation gate refused (the batch's `rejected_snaps`: a beacon implausibly far from the estimate); "
        "absent otherwise.")


class SkippedScan(BaseModel):
    index: int = Field(description="Index of the scan in the batch's `scans`.")
    reason: str


class BatchResult(BaseModel):
    seq: int
    estimate: EstimateOut | None = Field(
        description="The session's estimate after the batch; null only while a session without `initial` "
        "has not yet had a scan that gave a fix."
    )
    applied_steps: int
    applied_scans: int
    skipped_scans: list[SkippedScan] = Field(
        [], description="Scans that gave no fix (no ready model, no known transmitter), with why."
    )
    rejected_fixes: list[SkippedScan] = Field(
        [], description="Applied scans whose fingerprint fix the innovation gate refused as an outlier "
        "(their beacon ranges still applied), with why."
    )
    rejected_snaps: list[SkippedScan] = Field(
        [], description="Extension: applied scans whose landmark snap (an iBeacon of the site heard strongly "
        "enough to place the phone at it) the innovation gate refused, the beacon being implausibly far from "
        "the estimate (a misplaced beacon, or a reading through a wall or a body), with why. Self-calibrating "
        "filters only (`ekf`, `ukf`, `pf`, `skpf`); the seed forms restart on every snap."
    )


class SessionOut(BaseModel):
    id: str
    site_id: int
    filter: str
    model_id: int | None
    status: Literal["open", "closed"]
    estimate: EstimateOut | None = None
    created_at: datetime
    last_seq: int = Field(description="Highest batch seq applied (-1: none yet).")
    track_length: int = Field(description="Estimates in the track.")
    filter_params: dict[str, int | float] | None = Field(
        None, description="Extension. The tracker parameters the session was opened with, when it was given "
        "any (absent: the defaults); session lists leave them out.")


# --- service ---------------------------------------------------------------------------


class Health(BaseModel):
    status: Literal["ok"]


# --- models and locate -------------------------------------------------------------------


#: the largest integer every JSON reader keeps exactly (an IEEE double's); a model's params are stored as JSON
MAX_JSON_INT = 2**53


def _storable(value: Any, path: str = "params") -> None:
    """ValueError naming the first value of a model's params that JSON cannot carry faithfully:
    an integer beyond ±2⁵³ or a float that is not finite (nested lists and objects are walked)."""
    if isinstance(value, bool) or isinstance(value, str) or value is None:
        return
    if isinstance(value, int):
        if abs(value) > MAX_JSON_INT:
            raise ValueError(f"{path} = {value} is out of range (an integer must be within ±2^53)")
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{path} must be a finite number")
    elif isinstance(value, dict):
        for k, v in value.items():
            _storable(v, f"{path}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _storable(v, f"{path}.{i}")


def _storable_params(params: dict[str, Any]) -> dict[str, Any]:
    _storable(params)
    return params


class ModelIn(Strict):
    algorithm: Annotated[str, StringConstraints(min_length=1, max_length=40)] = Field(
        "wknn", description="The fingerprint algorithm to train (default `wknn`, extension: the field was required).",
        json_schema_extra=_ALGORITHM_ENUM)
    params: Annotated[dict[str, Any], Field(max_length=50), AfterValidator(_storable_params)] = {}
    use_heading: bool = False
    kinds: Annotated[list[Literal["wifi", "ble"]], Field(min_length=1, max_length=2)] | None = None
    include_crowd: bool = Field(True, description="Train on crowdsourced fingerprints too (extension).")
    activate: Activation = Field("if_none", description=(
        "When the trained model becomes the site's active one (extension): `if_none` (default) when the site has "
        "no active model; `if_better` also when its held-out mean error is no worse than the active model's; "
        "`always`; `never`. The decision and its figures are in the model's `metrics.activation`."))


class ActivationOut(BaseModel):
    requested: Activation
    activated: bool
    reason: str
    mean_error_m: float | None = Field(None, description="This model's held-out mean error (m).")
    active_model_id: int | None = Field(None, description="The model that was active when it was decided.")
    active_mean_error_m: float | None = Field(None, description="That model's held-out mean error (m).")


class CalibrationOut(BaseModel):
    scale: float
    floor_m: float
    walk_share: float | None = Field(None, ge=0, le=1, description=(
        "Share of the calibrated covariance that one device's fixes at least 10 m apart have in common "
        "(measured where each device is held out once; null otherwise). Sessions of the self-calibrating "
        "filters count it in their estimates' covariance. An `ekf` session with "
        "`filter_params` `walk_offset` 1 estimates the walk's fix offset from it, `walk_offset` 2 accounts for "
        "it without estimating it (for phones whose heading is calibrated)."))


class NisOut(BaseModel):
    mean: float | None
    median: float | None


class SurveyGridOut(BaseModel):
    building: int = 0
    floor: int
    deg: float = Field(description=(
        "The direction the floor's corridors run in, mod 90° (degrees clockwise from +y, in [−45, 45)), "
        "measured from the survey: the surveyors' moves between consecutive fingerprints of one device "
        "(`source` `walks`), else (none, or no grid in them) each surveyed position's nearest others "
        "(`points`). On a floor whose walls give no grid, `ekf`, `ukf`, `skpf` and `pf` sessions observe their "
        "heading bias on straight runs near it."))
    resultant: float = Field(description="How strongly the segments agree mod 90° (1: all along the grid; kept from 0.3).")
    segments: int
    source: Literal["walks", "points"]


class ModelMetrics(BaseModel):
    mean_error_m: float | None = None
    p50_error_m: float | None = None
    p90_error_m: float | None = None
    mapping_rate: float | None = None
    floor_hit_rate: float | None = None
    fit_time_s: float | None = None
    validated_on: int | None = Field(None, description="Held-out fingerprints the metrics come from.")
    building_hit_rate: float | None = None
    us_per_query: float | None = None
    held_out: str | None = Field(None, description="How the held-out sample was drawn.")
    held_out_pooled: bool | None = Field(None, description=(
        "True when the figures come from every device (or user) held out once, not from one split; "
        "`if_better` compares only figures of the same kind."))
    calibration: CalibrationOut | None = Field(None, description=(
        "The answers' covariance is scale·C + floor_m²·I of the model's own C, fitted on the held-out sample."))
    nis_raw: NisOut | None = Field(None, description="Held-out NIS rᵀC⁻¹r before calibration (calibrated: mean 2).")
    nis_calibrated: NisOut | None = Field(None, description="Held-out NIS after calibration.")
    activation: ActivationOut | None = Field(None, description="Whether training activated the model, and why.")
    survey_grid: list[SurveyGridOut] | None = Field(None, description=(
        "The floors whose survey shows a grid (extension); absent for a model trained before it was measured."))
    crowd_share: float | None = Field(None, ge=0.0, le=1.0, description=(
        "Extension: the share of the training fingerprints that are crowd estimates. A model with any answers "
        "anywhere: a tracking session's search circle does not restrict it (crowd positions are where earlier "
        "sessions believed they were). Absent for a model trained before it was recorded."))


class HeldOutPointErrorOut(BaseModel):
    building: int = 0
    floor: int
    x: float = Field(description=X_DOC)
    y: float = Field(description=Y_DOC)
    label: str
    n: int = Field(description="Held-out scans at this reference point.")
    mean_error_m: float = Field(description="Their mean horizontal error (m).")


class ModelOut(BaseModel):
    id: int
    site_id: int
    algorithm: str
    params: dict[str, Any]
    use_heading: bool
    kinds: list[str] | None
    include_crowd: bool
    status: Literal["queued", "training", "ready", "failed"]
    error: str | None = None
    active: bool
    trained_on: int
    metrics: ModelMetrics | None = None
    activate: Activation = "if_none"
    created_at: datetime
    updated_at: datetime


class LocateIn(Strict):
    rss: Annotated[Rss, Field(max_length=2048)]
    heading_deg: Degrees | None = None
    model_id: DbId | None = None


class CandidateOut(BaseModel):
    label: str | None
    x: float
    y: float
    floor: int
    building: int = Field(0, description=BUILDING_DOC)
    probability: float


class LocateOut(BaseModel):
    x: float = Field(description=X_DOC)
    y: float = Field(description=Y_DOC)
    floor: int
    building: int = Field(0, description="Extension: the building of `floor`, chosen first (building → floor → "
                          "position: the floor and the position always belong to it).")
    covariance: list[list[float]] = Field(description=COV_DOC)
    model_id: int
    algorithm: str
    reference_point: str | None = None
    candidates: list[CandidateOut] = []
    in_coverage: bool | None = Field(
        None, description="Extension: false when the scan resembles nothing surveyed (the answer is then only the "
        "nearest surveyed place): `coverage_ratio` > 1. Null when the model cannot tell (every algorithm but "
        "`wknn` and `knn`, which shares its search, or a model trained on too little to measure).")
    coverage_ratio: float | None = Field(
        None, description="Extension: the scan's RSS distance to the nearest surveyed fingerprint divided by the "
        "model's coverage threshold, the distance that 99 % of scans held out at unsurveyed reference points stayed "
        "within when the model was trained: 0 = a surveyed scan exactly, ≤ 1 in coverage. Null when "
        "`in_coverage` is.")
