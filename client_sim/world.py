"""The simulated world: sites with floors, walls, transmitters, reference points and routes.

Coordinates follow API.md: metres, x east, y north, integer floors (0 = ground).
Built-in scenarios mirror the kinds of test sites in the literature:

* ``open_room`` — one hall, every transmitter in line of sight, good signal.
* ``corridor_loop`` — a corridor ring around a block of rooms; transmitters sit in
  the rooms behind walls, packet loss rises with distance (poor signal).
* ``multi_floor`` — three floors joined by a stair, transmitters on every floor.

A world can also be loaded from / saved to JSON (:func:`load_world`, :meth:`World.to_json`).
"""

from __future__ import annotations

import errno
import json
import math
from dataclasses import asdict, dataclass, field
from itertools import pairwise
from pathlib import Path

BLE_UUID = "f7826da6-4fa2-4e98-8024-bc5b71e0893e"

Wall = tuple[float, float, float, float]
Waypoint = tuple[float, float, int]


@dataclass(frozen=True)
class Transmitter:
    """A WiFi AP or iBeacon; ``tx_power_dbm`` is R0, the RSS at 1 m."""

    id: str
    kind: str  # "wifi" | "ble"
    floor: int
    x: float
    y: float
    tx_power_dbm: float
    path_loss_exponent: float

    def to_api(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Floor:
    level: int
    name: str
    width_m: float
    height_m: float
    walls: tuple[Wall, ...] = ()

    def to_api(self) -> dict:
        return {
            "level": self.level,
            "name": self.name,
            "width_m": self.width_m,
            "height_m": self.height_m,
            "walls": [list(w) for w in self.walls],
        }


@dataclass(frozen=True)
class RadioParams:
    """Propagation and receiver parameters of a site (see :mod:`client_sim.radio`)."""

    wall_loss_db: float = 5.0  # per wall crossed
    floor_loss_db: float = 15.0  # per floor slab crossed
    floor_height_m: float = 3.5
    shadowing_sigma_db: float = 3.0  # spatially correlated part
    shadowing_corr_m: float = 3.0  # correlation length of the shadowing field
    temporal_sigma_db: float = 2.0  # fresh noise at every scan
    body_loss_db: float = 6.0  # extra loss with the walker's body between phone and transmitter
    wifi_threshold_dbm: float = -95.0
    ble_threshold_dbm: float = -100.0
    loss_base: float = 0.02  # per-scan packet loss at zero distance
    loss_per_m: float = 0.0  # added per metre of distance
    loss_max: float = 0.9


@dataclass(frozen=True)
class World:
    """One site: floors, transmitters, survey reference points, walking routes, radio."""

    name: str
    floors: tuple[Floor, ...]
    transmitters: tuple[Transmitter, ...]
    reference_points: tuple[Waypoint, ...]
    routes: tuple[tuple[Waypoint, ...], ...]
    radio: RadioParams = field(default_factory=RadioParams)
    magnetic_north_deg: float = 0.0  # heading of magnetic north in the site frame
    seed: int = 0  # fixes the shadowing field and magnetic disturbances

    def floor(self, level: int) -> Floor:
        for f in self.floors:
            if f.level == level:
                return f
        raise KeyError(f"no floor {level} in {self.name}")

    def site_payload(self, name: str | None = None) -> dict:
        """Body of ``POST /api/v1/sites`` for this world."""
        return {
            "name": name or self.name,
            "floors": [f.to_api() for f in self.floors],
            "transmitters": [t.to_api() for t in self.transmitters],
        }

    def to_dict(self) -> dict:
        d = asdict(self)
        d["floors"] = [dict(asdict(f), walls=[list(w) for w in f.walls]) for f in self.floors]
        d["reference_points"] = [list(p) for p in self.reference_points]
        d["routes"] = [[list(p) for p in r] for r in self.routes]
        return d

    def to_json(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))


def world_from_dict(d: dict) -> World:
    return World(
        name=d["name"],
        floors=tuple(
            Floor(f["level"], f.get("name", str(f["level"])), f["width_m"], f["height_m"],
                  tuple((float(x0), float(y0), float(x1), float(y1)) for x0, y0, x1, y1 in f.get("walls", [])))
            for f in d["floors"]
        ),
        transmitters=tuple(Transmitter(**t) for t in d["transmitters"]),
        reference_points=tuple((float(p[0]), float(p[1]), int(p[2])) for p in d.get("reference_points", [])),
        routes=tuple(tuple((float(p[0]), float(p[1]), int(p[2])) for p in r) for r in d.get("routes", [])),
        radio=RadioParams(**d.get("radio", {})),
        magnetic_north_deg=float(d.get("magnetic_north_deg", 0.0)),
        seed=int(d.get("seed", 0)),
    )


def load_world(path: str | Path) -> World:
    return world_from_dict(json.loads(Path(path).read_text()))


# ---------------------------------------------------------------- scenario helpers


def wifi(i: int, floor: int, x: float, y: float, r0: float = -40.0, gamma: float = 2.5) -> Transmitter:
    return Transmitter(f"wifi:02:00:00:00:{floor:02x}:{i:02x}", "wifi", floor, x, y, r0, gamma)


def ble(i: int, floor: int, x: float, y: float, r0: float = -62.0, gamma: float = 2.2) -> Transmitter:
    return Transmitter(f"ble:{BLE_UUID}:{100 + floor}:{i}", "ble", floor, x, y, r0, gamma)


def box(x0: float, y0: float, x1: float, y1: float) -> tuple[Wall, ...]:
    return ((x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0))


def grid(x0: float, y0: float, x1: float, y1: float, step: float, floor: int) -> list[Waypoint]:
    nx, ny = int(round((x1 - x0) / step)), int(round((y1 - y0) / step))
    return [(x0 + i * step, y0 + j * step, floor) for j in range(ny + 1) for i in range(nx + 1)]


def ring(x0: float, y0: float, x1: float, y1: float, step: float, floor: int) -> list[Waypoint]:
    """Points every ``step`` m along the rectangle (x0,y0)-(x1,y1), counter-clockwise."""
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
    pts: list[Waypoint] = []
    for (ax, ay), (bx, by) in pairwise(corners):
        n = max(1, int(round(math.hypot(bx - ax, by - ay) / step)))
        pts += [(ax + (bx - ax) * k / n, ay + (by - ay) * k / n, floor) for k in range(n)]
    return pts


# ---------------------------------------------------------------- built-in scenarios


def open_room() -> World:
    """A 20 × 15 m hall, all transmitters in line of sight, low noise, little loss."""
    w, h = 20.0, 15.0
    aps = [wifi(i, 0, x, y) for i, (x, y) in enumerate([(1, 1), (19, 1), (19, 14), (1, 14), (10, 7.5), (10, 1)])]
    beacons = [ble(i, 0, x, y) for i, (x, y) in enumerate(
        [(0.5, 7.5), (19.5, 7.5), (5, 0.5), (15, 0.5), (5, 14.5), (15, 14.5), (10, 14.5), (10, 4)])]
    return World(
        name="open_room",
        floors=(Floor(0, "hall", w, h, box(0, 0, w, h)),),
        transmitters=tuple(aps + beacons),
        reference_points=tuple(grid(2, 2, 18, 13, 2.0, 0)[:: 1]),
        routes=(
            ((3, 3, 0), (17, 3, 0), (17, 12, 0), (3, 12, 0), (3, 3, 0)),
            ((3, 3, 0), (17, 12, 0), (17, 3, 0), (3, 12, 0), (10, 7, 0)),
            ((10, 2.5, 0), (10, 12.5, 0), (4, 12.5, 0), (4, 7, 0), (16, 7, 0)),
        ),
        radio=RadioParams(shadowing_sigma_db=2.0, temporal_sigma_db=1.5, body_loss_db=4.0, loss_base=0.01),
        seed=11,
    )


def corridor_loop() -> World:
    """A 2.5 m wide corridor ring around a 40 × 30 m block; transmitters behind walls."""
    W, H, c = 40.0, 30.0, 2.5
    walls = box(0, 0, W, H) + box(c, c, W - c, H - c)
    # room partitions inside the central block and outside rooms' walls
    walls += tuple((x, c, x, H - c) for x in (12.0, 20.0, 28.0))
    walls += ((c, 15.0, W - c, 15.0),)
    aps = [wifi(i, 0, x, y, r0=-38.0, gamma=3.0) for i, (x, y) in enumerate(
        [(7, 8), (16, 8), (24, 8), (33, 8), (7, 22), (16, 22), (24, 22), (33, 22)])]
    beacons = [ble(i, 0, x, y, r0=-60.0, gamma=2.5) for i, (x, y) in enumerate(
        [(0.3, 15), (39.7, 15), (10, 0.3), (30, 0.3), (10, 29.7), (30, 29.7)])]
    mid = c / 2
    loop = ((mid, mid, 0), (W - mid, mid, 0), (W - mid, H - mid, 0), (mid, H - mid, 0), (mid, mid, 0))
    return World(
        name="corridor_loop",
        floors=(Floor(0, "ground", W, H, walls),),
        transmitters=tuple(aps + beacons),
        reference_points=tuple(ring(mid, mid, W - mid, H - mid, 2.0, 0)),
        routes=(loop, tuple(reversed(loop)), loop[2:] + loop[1:3]),
        radio=RadioParams(wall_loss_db=6.0, shadowing_sigma_db=4.0, temporal_sigma_db=3.0,
                          body_loss_db=8.0, loss_base=0.05, loss_per_m=0.02),
        magnetic_north_deg=-12.0,
        seed=23,
    )


def multi_floor() -> World:
    """Three 30 × 20 m floors, each a corridor with rooms either side; a stair at x≈28."""
    W, H = 30.0, 20.0
    floors, txs, rps = [], [], []
    for level in range(3):
        walls = box(0, 0, W, H) + ((0, 8.5, 26, 8.5), (0, 11.5, 26, 11.5))
        walls += tuple((x, 0, x, 8.5) for x in (8.0, 16.0)) + tuple((x, 11.5, x, H) for x in (8.0, 16.0))
        floors.append(Floor(level, f"level {level}", W, H, walls))
        txs += [wifi(i, level, x, y, r0=-40.0, gamma=2.8) for i, (x, y) in enumerate([(4, 4), (20, 4), (12, 16), (27, 16)])]
        txs += [ble(i, level, x, y) for i, (x, y) in enumerate([(2, 10), (14, 10), (25, 10), (28, 3)])]
        rps += [(x, 10.0, level) for x in range(2, 27, 2)] + [(28.0, y, level) for y in (4.0, 8.0, 12.0, 16.0)]
    return World(
        name="multi_floor",
        floors=tuple(floors),
        transmitters=tuple(txs),
        reference_points=tuple(rps),
        routes=(  # a segment whose end floor differs is the stair: the floor switches halfway
            ((2, 10, 0), (28, 10, 0), (28, 17, 1), (28, 10, 1), (2, 10, 1)),
            ((2, 10, 1), (28, 10, 1), (28, 17, 2), (28, 10, 2), (2, 10, 2)),
            ((24, 10, 2), (2, 10, 2), (28, 10, 2), (28, 3, 1), (28, 10, 1), (6, 10, 1)),
        ),
        radio=RadioParams(wall_loss_db=5.0, floor_loss_db=15.0, loss_base=0.03, loss_per_m=0.01),
        magnetic_north_deg=5.0,
        seed=37,
    )


SCENARIOS = {"open_room": open_room, "corridor_loop": corridor_loop, "multi_floor": multi_floor}


def get_world(name_or_path: str) -> World:
    """A built-in scenario by name, or a world JSON file by path."""
    if name_or_path in SCENARIOS:
        return SCENARIOS[name_or_path]()
    if not Path(name_or_path).is_file():
        raise FileNotFoundError(errno.ENOENT, f"neither a scenario ({', '.join(SCENARIOS)}) nor a world file",
                                name_or_path)
    return load_world(name_or_path)
