"""Walkers: a gait per person, a walk along a route's waypoints, and its ground truth.

A walk is a sequence of steps. Step ``i`` lasts from ``t[i-1]`` to ``t[i]`` (its
heel strike); the walker moves along the chord from ``pos[i-1]`` to ``pos[i]``, with
heading ``heading[i]``. During the first 30 % of a step the body turns from the
previous heading to the new one, so mid-step (where the phone sees the acceleration
peak) the heading is already the step's heading. The walker stands still for
``stand_s`` before the first and after the last step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .world import Waypoint

TURN_FRACTION = 0.3


@dataclass(frozen=True)
class Gait:
    """One person's walking: mean cadence and step length, and their per-step spread."""

    step_freq_hz: float = 1.8
    step_length_m: float = 0.7
    freq_jitter: float = 0.05  # relative std per step
    length_jitter: float = 0.05

    @staticmethod
    def random(rng: np.random.Generator) -> Gait:
        return Gait(
            step_freq_hz=float(rng.uniform(1.6, 2.1)),
            step_length_m=float(rng.uniform(0.6, 0.8)),
            freq_jitter=float(rng.uniform(0.02, 0.06)),
            length_jitter=float(rng.uniform(0.02, 0.06)),
        )


@dataclass
class Walk:
    """Ground truth of a walk. Index 0 is the start pose; steps are 1..n."""

    t: np.ndarray  # (n+1,) heel-strike times; t[0] = start of the first step
    xy: np.ndarray  # (n+1, 2) positions after each step
    floor: np.ndarray  # (n+1,) floor after each step
    heading_deg: np.ndarray  # (n+1,) heading of each step (index 0: initial heading)
    length_m: np.ndarray  # (n+1,) distance walked in each step (index 0: 0)
    stand_s: float = 2.0

    @property
    def n_steps(self) -> int:
        return len(self.t) - 1

    @property
    def t_start(self) -> float:
        return float(self.t[0] - self.stand_s)

    @property
    def t_end(self) -> float:
        return float(self.t[-1] + self.stand_s)

    def step_index(self, t: float) -> int:
        """The step in progress at time ``t`` (0 before the first step, n+1 after the last)."""
        return int(np.searchsorted(self.t, t, side="right"))

    def pose_at(self, t: float) -> tuple[float, float, int, float]:
        """(x, y, floor, heading_deg) at time ``t``, interpolated along the current step."""
        i = self.step_index(t)
        if i == 0:
            return float(self.xy[0, 0]), float(self.xy[0, 1]), int(self.floor[0]), float(self.heading_deg[0])
        if i > self.n_steps:
            return float(self.xy[-1, 0]), float(self.xy[-1, 1]), int(self.floor[-1]), float(self.heading_deg[-1])
        phase = (t - self.t[i - 1]) / (self.t[i] - self.t[i - 1])
        x, y = self.xy[i - 1] + phase * (self.xy[i] - self.xy[i - 1])
        floor = self.floor[i] if phase >= 0.5 else self.floor[i - 1]
        return float(x), float(y), int(floor), heading_during_step(self.heading_deg[i - 1], self.heading_deg[i], phase)

    def heading_rate_dps(self, t: np.ndarray) -> np.ndarray:
        """True yaw rate (deg/s, clockwise positive) at times ``t``: nonzero only while turning."""
        t = np.asarray(t, dtype=float)
        i = np.searchsorted(self.t, t, side="right")
        rate = np.zeros_like(t)
        inside = (i > 0) & (i <= self.n_steps)
        ii = i[inside]
        dur = self.t[ii] - self.t[ii - 1]
        phase = (t[inside] - self.t[ii - 1]) / dur
        dh = wrap_deg(self.heading_deg[ii] - self.heading_deg[ii - 1])
        turning = phase < TURN_FRACTION
        rate[inside] = np.where(turning, dh / (TURN_FRACTION * dur), 0.0)
        return rate

    def to_dict(self) -> dict:
        return {k: getattr(self, k).tolist() for k in ("t", "xy", "floor", "heading_deg", "length_m")}


def wrap_deg(a):
    """Wrap an angle (or array) to (−180, 180]."""
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def heading_during_step(h0: float, h1: float, phase: float) -> float:
    s = min(1.0, phase / TURN_FRACTION)
    return float((h0 + s * wrap_deg(h1 - h0)) % 360.0)


def walk_route(route: list[Waypoint] | tuple[Waypoint, ...], gait: Gait, rng: np.random.Generator,
               t0: float = 0.0, stand_s: float = 2.0) -> Walk:
    """Walk the waypoints in order, one step at a time, with per-step length and cadence.

    Every step covers its length along the polyline; a segment whose end waypoint is on
    another floor is a stair and the floor switches at its midpoint.
    """
    pts = np.array([[p[0], p[1]] for p in route], dtype=float)
    floors = [int(p[2]) for p in route]
    seg_len = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1]

    def point(s: float) -> tuple[np.ndarray, int]:
        k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg_len) - 1)
        frac = (s - cum[k]) / seg_len[k] if seg_len[k] > 0 else 1.0
        floor = floors[k + 1] if frac >= 0.5 else floors[k]
        return pts[k] + frac * (pts[k + 1] - pts[k]), floor

    first = pts[1] - pts[0]
    ts, xys, fls, hds, lens = [t0 + stand_s], [pts[0].copy()], [floors[0]], [bearing(first)], [0.0]
    s, t = 0.0, t0 + stand_s
    while s < total - 1e-9:
        length = gait.step_length_m * (1.0 + gait.length_jitter * rng.standard_normal())
        if total - (s + length) < 0.5 * gait.step_length_m:  # no stub step at the end
            length = total - s
        s += length
        xy, fl = point(s)
        t += 1.0 / (gait.step_freq_hz * (1.0 + gait.freq_jitter * rng.standard_normal()))
        d = xy - xys[-1]
        ts.append(t)
        xys.append(xy)
        fls.append(fl)
        hds.append(bearing(d) if np.hypot(*d) > 1e-6 else hds[-1])
        lens.append(length)
    return Walk(np.array(ts), np.array(xys), np.array(fls), np.array(hds), np.array(lens), stand_s)


def bearing(d: np.ndarray) -> float:
    return float(math.degrees(math.atan2(d[0], d[1])) % 360.0)


def route_variant(routes: tuple[tuple[Waypoint, ...], ...], rng: np.random.Generator) -> tuple[Waypoint, ...]:
    """A scenario route picked at random, walked forwards or backwards (crowd walkers)."""
    route = routes[int(rng.integers(len(routes)))]
    return route[::-1] if rng.random() < 0.5 else route
