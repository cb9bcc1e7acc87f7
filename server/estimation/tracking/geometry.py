"""Wall geometry: segment crossing tests and the wall-side constraint.

Walls are line segments [x1, y1, x2, y2] in site metres (one list per floor).
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def segments_cross(start: np.ndarray, end: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Whether the move start → end crosses the wall [x1, y1, x2, y2], element by element
    (arrays (..., 2), (..., 2) and (..., 4) that broadcast together).

    Touching a wall at an end point counts as crossing; moves parallel to (and
    overlapping) a wall do not.
    """
    r = end - start
    q = walls[..., 0:2]
    s = walls[..., 2:4] - q
    denom = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    qp = q - start
    t_num = qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]
    u_num = qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]
    ok = np.abs(denom) > _EPS
    safe = np.where(ok, denom, 1.0)
    t = t_num / safe
    u = u_num / safe
    return np.asarray(ok & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1))


def crosses_walls(start: np.ndarray, end: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """For moves start[i] → end[i] (arrays (n, 2)), whether each move crosses any wall
    (``segments_cross`` against every wall; ``floorplan.WallIndex`` for many walls)."""
    start = np.atleast_2d(start)
    end = np.atleast_2d(end)
    if walls.shape[0] == 0:
        return np.zeros(start.shape[0], dtype=bool)
    return np.asarray(segments_cross(start[:, None, :], end[:, None, :], walls[None, :, :]).any(axis=1))


def side_of(point, wall) -> float:
    """+1 if point is left of the directed wall (x1,y1)→(x2,y2), −1 if right, 0 on it."""
    x1, y1, x2, y2 = (float(v) for v in wall)
    cross = (x2 - x1) * (point[1] - y1) - (y2 - y1) * (point[0] - x1)
    return float(np.sign(cross))


def on_wrong_side(points, wall, side: float) -> np.ndarray:
    """For points (n, 2): whether each is off ``side`` (+1 left / −1 right) of a wall
    segment within its extent (its perpendicular foot falls on the segment). Beyond
    the segment's ends nothing is behind the wall."""
    p = np.atleast_2d(np.asarray(points, dtype=float))
    w = np.asarray(wall, dtype=float)
    a, d = w[:2], w[2:] - w[:2]
    rel = p - a
    t = rel @ d / max(float(d @ d), _EPS)
    cross = d[0] * rel[:, 1] - d[1] * rel[:, 0]
    return (t >= 0) & (t <= 1) & (np.sign(cross) != side)


def enforce_side(point, wall, side: float, margin_m: float = 0.05) -> tuple[np.ndarray, bool]:
    """Keep ``point`` on ``side`` (+1 left / −1 right) of a wall segment.

    If the point lies on the wrong side within the extent of the segment
    (``on_wrong_side``), it is moved to its perpendicular foot plus ``margin_m``
    towards the allowed side; otherwise it is left alone. Returns (point, moved).
    """
    p = np.asarray(point, dtype=float).copy()
    a = np.asarray(wall[:2], dtype=float)
    d = np.asarray(wall[2:], dtype=float) - a
    length2 = float(d @ d)
    if length2 < _EPS or side == 0 or not on_wrong_side(p, wall, side)[0]:
        return p, False
    foot = a + float((p - a) @ d) / length2 * d
    normal = np.array([-d[1], d[0]]) / np.sqrt(length2)  # points to the left
    return foot + side * margin_m * normal, True
