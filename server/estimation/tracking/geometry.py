"""Wall geometry: segment crossing tests, the wall-side constraint, and a Gaussian
truncated to a half-plane (how the Kalman-family trackers keep to walkable space).

Walls are line segments [x1, y1, x2, y2] in site metres (one list per floor).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erfcx

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


def crosses_any(start, end, walls: np.ndarray) -> bool:
    return bool(crosses_walls(np.asarray(start, float), np.asarray(end, float), walls)[0])


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


def first_wall_crossed(start, end, walls: np.ndarray, margin_m: float = 0.05) -> tuple[np.ndarray, float] | None:
    """The first wall the move start → end crosses, as the half-plane on ``start``'s side
    ``nᵀp ≥ c`` (n the unit normal towards ``start``, c the wall's line pulled ``margin_m``
    towards start); None when it crosses none."""
    p0, p1 = np.asarray(start, float), np.asarray(end, float)
    crossed = np.flatnonzero(segments_cross(p0, p1, np.asarray(walls, float).reshape(-1, 4)))
    if len(crossed) == 0:
        return None
    w = walls[crossed]
    a, d = w[:, :2], w[:, 2:] - w[:, :2]
    r = p1 - p0
    denom = r[0] * d[:, 1] - r[1] * d[:, 0]
    qp = a - p0
    t = np.where(np.abs(denom) > _EPS, (qp[:, 0] * d[:, 1] - qp[:, 1] * d[:, 0]) / np.where(denom == 0, 1.0, denom),
                 0.0)
    k = int(np.argmin(t))
    dx, dy = d[k]
    length = math.hypot(dx, dy)
    if length < _EPS:
        return None
    n = np.array([-dy, dx]) / length
    offset = float(n @ a[k])
    if float(n @ p0) < offset:
        n, offset = -n, -offset
    return n, offset + margin_m


def truncate_halfplane(x: np.ndarray, P: np.ndarray, normal, c: float) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian N(x, P) conditioned on nᵀx[:2] ≥ c, moment-matched (PDF truncation,
    Simon & Simon 2010): the 1-D marginal u = nᵀx[:2] ~ N(μ, σ²) is truncated to u ≥ c, and
    its new mean and variance are spread over the whole state through P's correlations, so a
    walker pushed back from a wall also teaches the states that drove it there (heading bias,
    step scale). ``normal`` must be a unit vector."""
    n = np.asarray(normal, float).reshape(2)
    h = np.zeros(len(x))
    h[:2] = n
    Ph = P @ h
    var = float(h @ Ph)
    if not var > 0.0:
        return x.copy(), P.copy()
    sd = math.sqrt(var)
    mu = float(h @ x)
    alpha = (c - mu) / sd
    # λ = φ(α)/(1 − Φ(α)), written with erfcx so it stays finite far into the tail
    lam = math.sqrt(2.0 / math.pi) / float(erfcx(alpha / math.sqrt(2.0)))
    new_mu = mu + sd * lam
    new_var = var * max(1.0 + alpha * lam - lam * lam, 1e-9)
    k = Ph / var
    x_new = x + k * (new_mu - mu)
    P_new = P - np.outer(k, k) * (var - new_var)
    return x_new, 0.5 * (P_new + P_new.T)
