"""The relational schema (SQLAlchemy 2 ORM). Alembic migrations mirror these classes."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_revision() -> str:
    """A fresh site revision: random, so a site id that SQLite reuses after a delete never
    matches a revision cached for the deleted site."""
    return uuid.uuid4().hex


class UtcDateTime(TypeDecorator):
    """A timezone-aware UTC timestamp on every backend (SQLite drops the zone on its own)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect) -> datetime | None:
        return value.astimezone(UTC) if value is not None else None

    def process_result_value(self, value: datetime | None, dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, list[Any]: JSON}


class ApiKey(Base):
    """An API key created from the CLI; only its SHA-256 is stored."""

    __tablename__ = "api_keys"
    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    scope: Mapped[str] = mapped_column(String(10))  # "admin" | "device"
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(UtcDateTime)


class Site(Base):
    __tablename__ = "sites"
    #: SQLite: ids of deleted sites are never reused (a client holding one cannot write into a new site)
    __table_args__ = {"sqlite_autoincrement": True}
    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    settings: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    #: changes whenever anything a fix depends on changes (settings, positioned transmitters,
    #: the active model), so a process may cache those per site and check one value per request
    revision: Mapped[str] = mapped_column(String(32), default=new_revision, server_default="")

    floors: Mapped[list[Floor]] = relationship(
        back_populates="site", order_by="(Floor.building, Floor.level)", cascade="all, delete-orphan", passive_deletes=True
    )


class Floor(Base):
    """A floor of a site: a (building, level) pair (0008; v1 sites are building 0)."""

    __tablename__ = "floors"
    __table_args__ = (UniqueConstraint("site_id", "building", "level", name="uq_floors_site_building_level"),)
    id: Mapped[int] = mapped_column(primary_key=True)
    site_id: Mapped[int] = mapped_column(ForeignKey("sites.id", ondelete="CASCADE"))
    building: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    level: Mapped[int] = mapped_column(Integer)
    name: Mapped[str | None] = mapped_column(String(200))
    width_m: Mapped[float | None] = mapped_column(Float)
    height_m: Mapped[float | None] = mapped_column(Float)
    walls: Mapped[list[Any]] = mapped_column(default=list)  # [[x1, y1, x2, y2], ...]
    walkable: Mapped[list[Any] | None] = mapped_column()  # polygons: [[[x, y], ...], ...] in site metres

    site: Mapped[Site] = relationship(back_populates="floors")


class Transmitter(Base):
    """A WiFi AP or iBeacon of a site; position and radio parameters are optional."""

    __tablename__ = "transmitters"
    __table_args__ = (UniqueConstraint("site_id", "tx_id"),)
    id: Mapped[int] = mapped_column(primary_key=True)
    site_id: Mapped[int] = mapped_column(ForeignKey("sites.id", ondelete="CASCADE"))
    tx_id: Mapped[str] = mapped_column(String(120))
    kind: Mapped[str] = mapped_column(String(10))
    building: Mapped[int | None] = mapped_column(Integer)  # set whenever floor is
    floor: Mapped[int | None] = mapped_column(Integer)
    x: Mapped[float | None] = mapped_column(Float)
    y: Mapped[float | None] = mapped_column(Float)
    tx_power_dbm: Mapped[float | None] = mapped_column(Float)
    path_loss_exponent: Mapped[float | None] = mapped_column(Float)


class ReferencePoint(Base):
    """A surveyed spot: fingerprints with the same (building, floor, label), or (building, floor,
    x, y), share one."""

    __tablename__ = "reference_points"
    __table_args__ = (UniqueConstraint("site_id", "building", "floor", "key",
                                       name="uq_reference_points_site_building_floor_key"),)
    id: Mapped[int] = mapped_column(primary_key=True)
    site_id: Mapped[int] = mapped_column(ForeignKey("sites.id", ondelete="CASCADE"))
    building: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    floor: Mapped[int] = mapped_column(Integer)
    key: Mapped[str] = mapped_column(String(240))  # "label:<label>" or "xy:<x>,<y>"
    label: Mapped[str | None] = mapped_column(String(200))
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)


class SurveyUpload(Base):
    """One accepted survey request; its idempotency key makes a retried upload harmless."""

    __tablename__ = "survey_uploads"
    __table_args__ = (UniqueConstraint("site_id", "idempotency_key"), Index("ix_survey_uploads_source", "site_id", "source"))
    id: Mapped[int] = mapped_column(primary_key=True)
    site_id: Mapped[int] = mapped_column(ForeignKey("sites.id", ondelete="CASCADE"))
    idempotency_key: Mapped[str | None] = mapped_column(String(200))
    #: SHA-256 of the request (format and body): a key replays only the request it came with
    request_hash: Mapped[str | None] = mapped_column(String(64))
    #: the file this request is a part of (``?source=``), and the file rows it stored: [[first, end), ...]
    source: Mapped[str | None] = mapped_column(String(200))
    source_rows: Mapped[list[Any] | None] = mapped_column()
    result: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class Fingerprint(Base):
    """One RSS scan at a known (survey) or estimated (crowd) position."""

    __tablename__ = "fingerprints"
    __table_args__ = (Index("ix_fingerprints_site_source", "site_id", "source"),)
    id: Mapped[int] = mapped_column(primary_key=True)
    site_id: Mapped[int] = mapped_column(ForeignKey("sites.id", ondelete="CASCADE"))
    source: Mapped[str] = mapped_column(String(10))  # "survey" | "crowd"
    reference_point_id: Mapped[int | None] = mapped_column(
        ForeignKey("reference_points.id", ondelete="CASCADE"), index=True
    )
    upload_id: Mapped[int | None] = mapped_column(ForeignKey("survey_uploads.id", ondelete="CASCADE"))
    building: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    floor: Mapped[int] = mapped_column(Integer)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    heading_deg: Mapped[float | None] = mapped_column(Float)
    t: Mapped[float | None] = mapped_column(Float)
    device: Mapped[str | None] = mapped_column(String(200))
    rss: Mapped[dict[str, Any]] = mapped_column()  # {tx_id: dBm}
    samples: Mapped[int] = mapped_column(Integer, default=1)  # crowd points merge several scans
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class Model(Base):
    """A trained (or training) fingerprint model of a site; the artifact lives apart.

    At most one model per site is active (a partial unique index enforces it); ids are never reused.
    """

    __tablename__ = "models"
    __table_args__ = (
        Index("uq_models_one_active", "site_id", unique=True, sqlite_where=text("active"),
              postgresql_where=text("active")),
        {"sqlite_autoincrement": True},  # SQLite: a deleted model's id is never given to another (0007)
    )
    id: Mapped[int] = mapped_column(primary_key=True)
    site_id: Mapped[int] = mapped_column(ForeignKey("sites.id", ondelete="CASCADE"), index=True)
    algorithm: Mapped[str] = mapped_column(String(40))
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    use_heading: Mapped[bool] = mapped_column(Boolean, default=False)
    kinds: Mapped[list[Any]] = mapped_column(default=list)
    include_crowd: Mapped[bool] = mapped_column(Boolean, default=True)
    status: Mapped[str] = mapped_column(String(10), default="queued")
    error: Mapped[str | None] = mapped_column(Text)
    active: Mapped[bool] = mapped_column(Boolean, default=False)
    trained_on: Mapped[int] = mapped_column(Integer, default=0)
    metrics: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    claimed_at: Mapped[datetime | None] = mapped_column(UtcDateTime)  # when a worker took the job
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow, onupdate=utcnow)


class ModelArtifact(Base):
    """The serialised trained model with its SHA-256, kept out of the hot ``models`` rows."""

    __tablename__ = "model_artifacts"
    model_id: Mapped[int] = mapped_column(ForeignKey("models.id", ondelete="CASCADE"), primary_key=True)
    sha256: Mapped[str] = mapped_column(String(64))
    blob: Mapped[bytes] = mapped_column(LargeBinary)


class TrackingSession(Base):
    """A walking session; its tracker state is stored so any server process can serve it."""

    __tablename__ = "tracking_sessions"
    __table_args__ = (Index("ix_tracking_sessions_owner_created", "owner_key", "created_at"),
                      Index("ix_tracking_sessions_created_id", "created_at", "id"))
    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    site_id: Mapped[int] = mapped_column(ForeignKey("sites.id", ondelete="CASCADE"), index=True)
    owner_key: Mapped[str] = mapped_column(String(64))  # hash of the key that opened it
    filter: Mapped[str] = mapped_column(String(20))
    model_id: Mapped[int | None] = mapped_column(ForeignKey("models.id", ondelete="SET NULL"))
    status: Mapped[str] = mapped_column(String(10), default="open")
    state: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    last_seq: Mapped[int] = mapped_column(Integer, default=-1)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    #: estimates in the track (the next estimate's idx); last_seq is the compare-and-set version
    track_length: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    closed_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    #: the tracker's state right after opening, for a replay (``estimation.replay``; PF sessions only, else NULL)
    opening_state: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))


class SessionBatch(Base):
    """One applied batch of a tracking session with the answer it got, so a replay gets it again."""

    __tablename__ = "session_batches"
    session_id: Mapped[str] = mapped_column(
        ForeignKey("tracking_sessions.id", ondelete="CASCADE"), primary_key=True
    )
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)
    answer: Mapped[dict[str, Any]] = mapped_column()
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    #: the batch as the tracker saw it, for a replay (``estimation.replay.RecordedBatch``; PF sessions only, else NULL)
    inputs: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))


class TrackEstimate(Base):
    """One estimate of a session's track (after a step, a scan, or the initial position)."""

    __tablename__ = "track_estimates"
    session_id: Mapped[str] = mapped_column(
        ForeignKey("tracking_sessions.id", ondelete="CASCADE"), primary_key=True
    )
    idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    seq: Mapped[int | None] = mapped_column(Integer)  # the batch that produced it (None: initial)
    t: Mapped[float | None] = mapped_column(Float)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    building: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    floor: Mapped[int] = mapped_column(Integer)
    covariance: Mapped[list[Any]] = mapped_column()
    source: Mapped[str] = mapped_column(String(10))  # "step" | "scan" | "init"
    #: a self-calibrating tracker's whole state here (``FullState.to_dict``), for the smoother; NULL otherwise
    state: Mapped[dict[str, Any] | None] = mapped_column(JSON)
