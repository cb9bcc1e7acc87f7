"""Radio propagation: what RSS a phone at a spot, walking a heading, measures.

``RSS = R0 − 10·γ·log10(d) − L_wall·n_walls − L_floor·n_floors + S(x, y) + B(heading) + ε``

* ``S`` — spatially correlated shadowing, a Gaussian random field per transmitter
  and floor (random Fourier features of a squared-exponential kernel), fixed by the
  world's seed: the same spot gives similar RSS on every visit, which is what makes
  fingerprinting work at all.
* ``B`` — body shadowing: the phone is held in front of the walker, so a transmitter
  behind the walker is attenuated by up to ``body_loss_db`` (``(1 − cos Δ)/2`` with Δ
  the angle between heading and bearing to the transmitter).
* ``ε`` — temporal noise, fresh at every scan.

A scan keeps readings above the detection threshold, then drops each with the
packet-loss probability ``loss_base + loss_per_m·d`` (clipped to ``loss_max``).
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np

from .world import Transmitter, World

N_FEATURES = 64  # random Fourier features per shadowing field


def walls_crossed(x0: float, y0: float, x1: float, y1: float, walls: np.ndarray) -> int:
    """Number of wall segments (rows x1,y1,x2,y2) the segment (x0,y0)-(x1,y1) crosses properly."""
    if len(walls) == 0:
        return 0
    px, py, qx, qy = walls[:, 0], walls[:, 1], walls[:, 2], walls[:, 3]

    def orient(ax, ay, bx, by, cx, cy):
        return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)

    d1 = orient(x0, y0, x1, y1, px, py)
    d2 = orient(x0, y0, x1, y1, qx, qy)
    d3 = orient(px, py, qx, qy, x0, y0)
    d4 = orient(px, py, qx, qy, x1, y1)
    return int(np.count_nonzero((d1 * d2 < 0) & (d3 * d4 < 0)))


def bearing_deg(x0: float, y0: float, x1: float, y1: float) -> float:
    """Heading (clockwise from +y) of the direction from (x0,y0) to (x1,y1)."""
    return math.degrees(math.atan2(x1 - x0, y1 - y0)) % 360.0


class RadioModel:
    """Deterministic mean RSS of a world plus the random parts of a scan."""

    def __init__(self, world: World):
        self.world = world
        self.p = world.radio
        self._walls = {f.level: np.array(f.walls, dtype=float).reshape(-1, 4) for f in world.floors}
        rng = np.random.default_rng([world.seed, 0x5AD0])
        n_tx, n_floor = len(world.transmitters), len(world.floors)
        # one field per (transmitter, receiving floor)
        self._k = rng.normal(0.0, 1.0 / self.p.shadowing_corr_m, size=(n_tx, n_floor, N_FEATURES, 2))
        self._phase = rng.uniform(0, 2 * math.pi, size=(n_tx, n_floor, N_FEATURES))
        self._floor_index = {f.level: i for i, f in enumerate(world.floors)}

    @cached_property
    def _index(self) -> dict[str, int]:
        return {t.id: i for i, t in enumerate(self.world.transmitters)}

    def shadowing_db(self, tx: Transmitter, x: float, y: float, floor: int) -> float:
        i, f = self._index[tx.id], self._floor_index[floor]
        arg = self._k[i, f] @ np.array([x, y]) + self._phase[i, f]
        return float(self.p.shadowing_sigma_db * math.sqrt(2.0 / N_FEATURES) * np.cos(arg).sum())

    def distance(self, tx: Transmitter, x: float, y: float, floor: int) -> float:
        dz = (floor - tx.floor) * self.p.floor_height_m
        return max(0.5, math.sqrt((x - tx.x) ** 2 + (y - tx.y) ** 2 + dz * dz))

    def mean_rss(self, tx: Transmitter, x: float, y: float, floor: int, heading_deg: float | None = None,
                 shadowing: bool = True) -> float:
        """Expected RSS (dBm) without temporal noise or loss; body shadowing if heading is given."""
        d = self.distance(tx, x, y, floor)
        rss = tx.tx_power_dbm - 10.0 * tx.path_loss_exponent * math.log10(d)
        if floor == tx.floor:
            rss -= self.p.wall_loss_db * walls_crossed(x, y, tx.x, tx.y, self._walls[floor])
        else:
            rss -= self.p.floor_loss_db * abs(floor - tx.floor)
        if shadowing:
            rss += self.shadowing_db(tx, x, y, floor)
        if heading_deg is not None:
            delta = math.radians(bearing_deg(x, y, tx.x, tx.y) - heading_deg)
            rss -= self.p.body_loss_db * (1.0 - math.cos(delta)) / 2.0
        return rss

    def scan(self, x: float, y: float, floor: int, heading_deg: float | None, kind: str,
             rng: np.random.Generator) -> dict[str, float]:
        """One scan of ``kind`` ("wifi" or "ble"): heard transmitter id → dBm (rounded to 0.1)."""
        threshold = self.p.wifi_threshold_dbm if kind == "wifi" else self.p.ble_threshold_dbm
        out: dict[str, float] = {}
        for tx in self.world.transmitters:
            if tx.kind != kind:
                continue
            rss = self.mean_rss(tx, x, y, floor, heading_deg) + rng.normal(0.0, self.p.temporal_sigma_db)
            loss = min(self.p.loss_max, self.p.loss_base + self.p.loss_per_m * self.distance(tx, x, y, floor))
            if rss < threshold or rng.random() < loss:
                continue
            out[tx.id] = round(min(0.0, max(-130.0, rss)), 1)
        return out
