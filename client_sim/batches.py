"""What a phone posts to a tracking session: its scans and its steps, in batches by phone time.

One batch maker serves the simulated phones (:mod:`client_sim.runs`) and the replayed
Microsoft walks (:mod:`client_sim.msft_eval`), so both send the same API.md batch body.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NotRequired, TypedDict

import numpy as np

from .pdr import PdrStep


class Scan(TypedDict):
    """One API.md scan item, kept as the JSON object it is sent as (``heading_deg`` only
    when the phone knows it: the simulated phones do, the Microsoft walks don't)."""

    t: float
    rss: dict[str, float]
    heading_deg: NotRequired[float]


@dataclass(frozen=True)
class Batch:
    """One ``POST /sessions/{sid}/batches`` body: ``seq`` and what the phone measured since the last one."""

    seq: int
    steps: tuple[PdrStep, ...]
    scans: tuple[Scan, ...]

    def to_api(self) -> dict[str, Any]:
        return {"seq": self.seq, "steps": [s.to_api() for s in self.steps], "scans": list(self.scans)}


def make_batches(steps: Sequence[PdrStep], scans: Sequence[Scan], t0: float, t1: float,
                 interval_s: float = 2.0) -> list[Batch]:
    """Batches every ``interval_s`` of phone time from ``t0`` (exclusive) to ``t1``, seq from 0.

    The session starts at ``t0``, so steps and scans at or before it are left out; each
    later one up to the last batch's end lands in exactly one batch.
    """
    edges = np.arange(t0 + interval_s, t1 + interval_s, interval_s)
    batches, lo = [], t0
    for seq, hi in enumerate(edges):
        batches.append(Batch(seq, tuple(s for s in steps if lo < s.t <= hi),
                             tuple(s for s in scans if lo < s["t"] <= hi)))
        lo = hi
    return batches
