"""Service settings, read from ``LOCALIZER_*`` environment variables."""

from __future__ import annotations

from functools import lru_cache
from typing import Annotated

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict


def _split_keys(value: object) -> object:
    if isinstance(value, str):
        return [k.strip() for k in value.split(",") if k.strip()]
    return value


class Settings(BaseSettings):
    """Everything an operator can set; defaults run a single process on SQLite."""

    model_config = SettingsConfigDict(env_prefix="LOCALIZER_", extra="ignore")

    database_url: str = Field(
        "sqlite:///./localizer.db",
        description="SQLAlchemy URL; SQLite file by default, postgresql+psycopg://... for production.",
    )
    admin_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Comma-separated bootstrap admin API keys."
    )
    device_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Comma-separated bootstrap device API keys."
    )
    max_body_mb: float = Field(64.0, gt=0, description="Largest request body accepted (MiB).")
    max_batch_body_kb: float = Field(4096.0, gt=0, description="Largest batch body accepted (KiB): fits 1,000 steps "
                                     "and 1,000 scans.")
    max_locate_body_kb: float = Field(256.0, gt=0, description="Largest locate body accepted (KiB).")
    body_read_timeout_s: float = Field(30.0, gt=0, description="A request body that stops arriving for this long is 408.")
    auth_failures_per_minute: int = Field(
        60, gt=0, description="Failed authentications one client address may make per minute before 429.")
    max_survey_rows: int = Field(100_000, gt=0, description="Most fingerprints in one survey upload.")
    embedded_worker: bool = Field(True, description="Train models in this server process's own worker.")
    training_poll_s: float = Field(2.0, gt=0, description="How often a worker looks for queued models.")
    training_stale_after_s: float = Field(
        90.0, gt=0, description="A job whose worker sent no heartbeat for this long (it died) is trained again; "
        "workers beat every sixth of it."
    )
    model_cache_size: int = Field(8, gt=0, description="Trained models kept loaded per process.")
    sqlite_busy_timeout_s: float = Field(
        5.0, gt=0, description="SQLite: a request that waits this long for the database's write lock (another "
        "writer holds it) is 503 with Retry-After, nothing stored; training and migrations wait 30 s.")

    _split = field_validator("admin_keys", "device_keys", mode="before")(_split_keys)

    @field_validator("database_url")
    @classmethod
    def _psycopg_driver(cls, url: str) -> str:
        """Plain ``postgresql://`` (or ``postgres://``) URLs use the installed psycopg 3 driver."""
        for prefix in ("postgresql://", "postgres://"):
            if url.startswith(prefix):
                return "postgresql+psycopg://" + url[len(prefix) :]
        return url

    @property
    def max_body_bytes(self) -> int:
        return int(self.max_body_mb * 1024 * 1024)


@lru_cache
def get_settings() -> Settings:
    return Settings()
