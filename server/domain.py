"""The service's domain types: what services, the store and routes pass between them.

Frozen dataclasses, grouped by aggregate. Estimation types (steps, scans, fixes,
estimates) live in ``server.estimation.types``; these are the service's own records.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from server.estimation.types import Estimate, ScanNote

# --- tracking sessions ---------------------------------------------------------------------


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

    def to_dict(self) -> dict[str, Any]:
        return {
            "seq": self.seq,
            "estimate": None if self.estimate is None else self.estimate.to_dict(),
            "applied_steps": self.applied_steps,
            "applied_scans": self.applied_scans,
            "skipped_scans": [{"index": n.index, "reason": n.reason} for n in self.skipped_scans],
            "rejected_fixes": [{"index": n.index, "reason": n.reason} for n in self.rejected_fixes],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BatchAnswer:
        """Answers stored before the innovation gate have no ``rejected_fixes``."""
        return cls(
            seq=d["seq"],
            estimate=None if d["estimate"] is None else Estimate.from_dict(d["estimate"]),
            applied_steps=d["applied_steps"],
            applied_scans=d["applied_scans"],
            skipped_scans=tuple(ScanNote(n["index"], n["reason"]) for n in d.get("skipped_scans", [])),
            rejected_fixes=tuple(ScanNote(n["index"], n["reason"]) for n in d.get("rejected_fixes", [])),
        )
