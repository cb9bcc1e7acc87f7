"""The building's grid: the direction its corridors run in, mod 90°, from its walls or its survey.

People walk along a rectilinear building's corridors, so a straight run of steps whose corrected
heading lies near a grid direction observes the PDR's heading bias (``selfcal.Calibrating``).
Headings and directions are a step's: degrees clockwise from +y; a grid direction g stands for
g + k·90°, reported in [−45°, 45°).

Two sources:

- **Walls** (a floor plan, `grid_direction_deg`): the length-weighted circular mean of 4θ over the
  walls, when its resultant is at least ``WALLS_MIN_RESULTANT`` (rectilinear walls agree mod 90°).
- **The survey** (`survey_grids`, for a floor without such walls): a survey records where people
  walked or stood. Where its fingerprints carry a device and a time, consecutive fingerprints of
  one device 0.3–10 m apart are the surveyor's moves (``walks``); where there are none or they agree on
  no grid, each surveyed position and its two nearest others within 5 m (``points``: a survey every
  few metres along corridors, or surveyors hopping between its reference points in any order).
  The grid is the kernel mode (3°) of those segments' length-weighted directions mod 90° — the
  mean is pulled by moves across open areas, the mode is the corridors' — accepted when their
  4θ resultant is at least ``SURVEY_MIN_RESULTANT``. On the MSFT site-1 fold maps the walks give
  10.75–11.50° against the plan's walls 10.83°, with resultants 0.37–0.51 (their nearest
  positions 0.20–0.32); a survey every 2 m along a rectangular loop gives its axes exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: walls have a grid when the resultant of their length-weighted 4θ is at least this
WALLS_MIN_RESULTANT = 0.4
#: a survey's segments have a grid when their resultant is at least this (module docstring)
SURVEY_MIN_RESULTANT = 0.3
#: a surveyor's move between two consecutive fingerprints of one device (m): shorter is standing
#: still, longer is a gap in the recording
MOVE_RANGE_M = (0.3, 10.0)
#: fewer walk segments than this on a floor: its surveyed positions' nearest neighbours instead
MIN_WALK_SEGMENTS = 20
#: a position's nearest neighbours that count, and how far they may be (m)
NEIGHBOURS = 2
NEIGHBOUR_MAX_M = 5.0
#: the kernel's bandwidth for the mode of the directions (degrees), and the grid it is evaluated on
MODE_BANDWIDTH_DEG = 3.0
MODE_STEP_DEG = 0.25


@dataclass(frozen=True)
class FloorGrid:
    """A floor's grid direction measured from its survey: ``source`` ``walks`` or ``points``,
    ``resultant`` how strongly its segments agree mod 90° (1: all along the grid), ``segments`` how many."""

    building: int
    floor: int
    deg: float
    resultant: float
    segments: int
    source: str


def _resultant(dx: np.ndarray, dy: np.ndarray, length: np.ndarray) -> tuple[float, float]:
    """The length-weighted mean of the unit vectors at 4θ: (its length over the total length, its angle / 4 in degrees)."""
    theta4 = 4.0 * np.arctan2(dx, dy)
    c, s, total = float(length @ np.cos(theta4)), float(length @ np.sin(theta4)), float(length.sum())
    if total <= 0:
        return 0.0, 0.0
    return math.hypot(c, s) / total, math.degrees(math.atan2(s, c)) / 4.0


def grid_direction_deg(walls: np.ndarray) -> float | None:
    """The walls' grid direction in [−45°, 45°), or None when they have none (their 4θ resultant
    below ``WALLS_MIN_RESULTANT``)."""
    walls = np.asarray(walls, float).reshape(-1, 4)
    if len(walls) == 0:
        return None
    dx, dy = walls[:, 2] - walls[:, 0], walls[:, 3] - walls[:, 1]
    strength, deg = _resultant(dx, dy, np.hypot(dx, dy))
    return deg if strength >= WALLS_MIN_RESULTANT else None


def mode_direction_deg(dx: np.ndarray, dy: np.ndarray, length: np.ndarray) -> float:
    """The kernel mode of the segments' length-weighted directions mod 90°, in [−45°, 45°)."""
    theta = np.degrees(np.arctan2(dx, dy)) % 90.0
    grid = np.arange(0.0, 90.0, MODE_STEP_DEG)
    offset = (grid[:, None] - theta[None, :] + 45.0) % 90.0 - 45.0
    density = np.exp(-0.5 * (offset / MODE_BANDWIDTH_DEG) ** 2) @ length
    return float((grid[int(np.argmax(density))] + 45.0) % 90.0 - 45.0)


def walk_segments(x: np.ndarray, y: np.ndarray, device: np.ndarray | None, t: np.ndarray | None) -> np.ndarray:
    """(n, 2) moves between consecutive fingerprints of one device by time, ``MOVE_RANGE_M`` long."""
    if device is None or t is None or len(x) < 2:
        return np.zeros((0, 2))
    known = np.array([d is not None for d in device]) & np.isfinite(np.asarray(t, float))
    if known.sum() < 2:
        return np.zeros((0, 2))
    dev = np.asarray([str(d) for d in np.asarray(device, object)[known]])
    order = np.lexsort((np.asarray(t, float)[known], dev))
    dev, px, py = dev[order], np.asarray(x, float)[known][order], np.asarray(y, float)[known][order]
    moves = np.column_stack((np.diff(px), np.diff(py)))[dev[1:] == dev[:-1]]
    length = np.hypot(moves[:, 0], moves[:, 1])
    return moves[(length >= MOVE_RANGE_M[0]) & (length <= MOVE_RANGE_M[1])]


def neighbour_segments(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n, 2) segments from each distinct surveyed position to its ``NEIGHBOURS`` nearest others within ``NEIGHBOUR_MAX_M``."""
    xy = np.unique(np.round(np.column_stack((x, y)).astype(float), 2), axis=0)
    if len(xy) < 2:
        return np.zeros((0, 2))
    k = min(NEIGHBOURS, len(xy) - 1)
    dist, idx = cKDTree(xy).query(xy, k=k + 1)
    dist, idx = dist[:, 1:], idx[:, 1:]
    near = (dist > 0) & (dist <= NEIGHBOUR_MAX_M)
    return (xy[idx] - xy[:, None, :])[near]


def _grid_of(segs: np.ndarray) -> tuple[float, float] | None:
    """(direction, resultant) of segments that agree on a grid, else None."""
    if len(segs) == 0:
        return None
    length = np.hypot(segs[:, 0], segs[:, 1])
    strength, _ = _resultant(segs[:, 0], segs[:, 1], length)
    if strength < SURVEY_MIN_RESULTANT:
        return None
    return mode_direction_deg(segs[:, 0], segs[:, 1], length), round(strength, 3)


def survey_grids(building: np.ndarray, floor: np.ndarray, x: np.ndarray, y: np.ndarray,
                 device: np.ndarray | None = None, t: np.ndarray | None = None) -> list[FloorGrid]:
    """Each floor's grid from its fingerprints: from its walks where it has at least
    ``MIN_WALK_SEGMENTS`` moves and they agree on one, else from its surveyed positions (a survey
    whose devices hop between reference points in any order shows its grid by where they stand,
    not by how they moved); floors where neither agrees have none (module docstring)."""
    building, floor = np.asarray(building, int), np.asarray(floor, int)
    out = []
    for b, f in sorted({(int(b), int(f)) for b, f in zip(building, floor, strict=True)}):
        on = (building == b) & (floor == f)
        segs = walk_segments(x[on], y[on], None if device is None else np.asarray(device, object)[on],
                             None if t is None else np.asarray(t, float)[on])
        source, found = "walks", _grid_of(segs) if len(segs) >= MIN_WALK_SEGMENTS else None
        if found is None:  # (the positions' neighbours only where the walks say nothing)
            segs = neighbour_segments(x[on], y[on])
            source, found = "points", _grid_of(segs)
        if found is not None:
            out.append(FloorGrid(b, f, found[0], found[1], len(segs), source))
    return out
