"""Crowdsourcing rules, pure functions (the server does the storage).

A crowd point is a ``CrowdPoint`` (``server.estimation.types``).

Gating (``gate``) keeps a drifting session from poisoning the map: the tracker's
estimate must be tight (covariance trace small) and agree with the fingerprint
model's fix for the same scan (same floor, distance small), its floor must be the one
of the strongest positioned transmitter the scan hears (where it hears one: a session
and a map that agree on the wrong floor must not teach the map more of it), and the
scan must hear enough transmitters. Merging (``find_merge_target``, ``merge_points``): a new point within 1 m of a stored
point on the same floor is averaged into the nearest one (position weighted by point
counts, RSS as a running mean per transmitter with its own count); otherwise it is
inserted.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from server.estimation.types import CrowdPoint


@dataclass(frozen=True)
class GateDecision:
    accepted: bool
    reason: str  # "ok" or why not

    def __bool__(self) -> bool:
        return self.accepted


def gate(
    estimate_mean,
    estimate_cov,
    fix_mean,
    rss: dict[str, float],
    *,
    max_cov_trace_m2: float = 2.0,
    max_disagreement_m: float = 3.0,
    min_transmitters: int = 3,
    level: tuple[int, int] | None = None,
    fix_level: tuple[int, int] | None = None,
    heard_level: tuple[int, int] | None = None,
) -> GateDecision:
    """Whether (estimate, scan) is confident enough to become a crowd fingerprint. ``level``: the
    estimate's (building, floor); ``fix_level``: the fix's; ``heard_level``: the strongest heard
    positioned transmitter's (``session.strongest_level``); each None: not checked."""
    if level is not None and fix_level is not None and fix_level != level:
        return GateDecision(False, f"estimate on level {level}, its fix on {fix_level}")
    if level is not None and heard_level is not None and heard_level != level:
        return GateDecision(False, f"the strongest positioned transmitter heard is on level {heard_level}, not {level}")
    trace = float(np.trace(np.asarray(estimate_cov, float)))
    if not math.isfinite(trace) or trace > max_cov_trace_m2:
        return GateDecision(False, f"covariance trace {trace:.2f} m² > {max_cov_trace_m2}")
    dist = float(np.hypot(*(np.asarray(estimate_mean, float) - np.asarray(fix_mean, float))))
    if dist > max_disagreement_m:
        return GateDecision(False, f"estimate and fix {dist:.2f} m apart > {max_disagreement_m}")
    if len(rss) < min_transmitters:
        return GateDecision(False, f"{len(rss)} transmitters < {min_transmitters}")
    return GateDecision(True, "ok")


def make_crowd_point(x: float, y: float, floor: int, rss: dict[str, float], building: int = 0) -> CrowdPoint:
    return CrowdPoint(float(x), float(y), int(floor), {k: float(v) for k, v in rss.items()}, 1, dict.fromkeys(rss, 1),
                      building=int(building))


def merge_points(stored: CrowdPoint, new: CrowdPoint) -> CrowdPoint:
    """``new`` averaged into ``stored``: position weighted by point counts, RSS by reading counts."""
    n1, n2 = stored.count, new.count
    c1, c2 = stored.tx_counts(), new.tx_counts()
    rss: dict[str, float] = {}
    counts: dict[str, int] = {}
    for tx in set(stored.rss) | set(new.rss):
        a, b = c1.get(tx, 0) if tx in stored.rss else 0, c2.get(tx, 0) if tx in new.rss else 0
        counts[tx] = a + b
        rss[tx] = (stored.rss.get(tx, 0.0) * a + new.rss.get(tx, 0.0) * b) / (a + b)
    return CrowdPoint(
        x=(stored.x * n1 + new.x * n2) / (n1 + n2),
        y=(stored.y * n1 + new.y * n2) / (n1 + n2),
        floor=stored.floor, rss=rss, count=n1 + n2, counts=counts, building=stored.building,
    )


def find_merge_target(stored: Sequence[CrowdPoint], new: CrowdPoint, radius_m: float = 1.0) -> int | None:
    """Index of the nearest stored point on the same floor within ``radius_m``, or None."""
    best, best_d = None, float("inf")
    for i, p in enumerate(stored):
        if p.floor != new.floor:
            continue
        d = math.hypot(p.x - new.x, p.y - new.y)
        if d <= radius_m and d < best_d:
            best, best_d = i, d
    return best

