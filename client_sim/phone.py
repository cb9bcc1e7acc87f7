"""One simulated phone on one walk: ground truth, raw IMU, on-phone PDR and RSS scans.

Everything a phone would send is derived from its own sensors: steps come from the
PDR on the synthesised IMU, and scans carry the PDR heading (not the true one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .batches import Batch, Scan, make_batches
from .imu import ImuParams, synthesize_imu
from .pdr import PdrConfig, PdrStep, heading_at, run_pdr
from .radio import RadioModel
from .walker import Gait, Walk, walk_route
from .world import Waypoint, World


@dataclass
class PhoneTrace:
    walk: Walk
    steps: list[PdrStep]
    scans: list[Scan]  # each with the PDR heading

    def truth_at(self, t: float) -> tuple[float, float, int]:
        x, y, floor, _ = self.walk.pose_at(t)
        return x, y, floor

    def batches(self, interval_s: float) -> list[Batch]:
        """Everything the phone measured on its walk, in batches every ``interval_s``."""
        return make_batches(self.steps, self.scans, self.walk.t_start, self.walk.t_end, interval_s)

    def dead_reckoning(self) -> np.ndarray:
        """PDR-only track (rows t, x, y) from the true start: the baseline a filter must beat."""
        x, y = self.walk.xy[0]
        rows = [(self.walk.t_start, x, y)]
        for s in self.steps:
            h = np.radians(s.heading_deg)
            x, y = x + s.length_m * np.sin(h), y + s.length_m * np.cos(h)
            rows.append((s.t, x, y))
        return np.array(rows)


def scan_times(t0: float, t1: float, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    """Scan instants at ``rate_hz`` with ±20 % jitter per interval (phones don't scan on a clock)."""
    if rate_hz <= 0:
        return np.array([])
    n = int((t1 - t0) * rate_hz * 1.3) + 2
    times = t0 + np.cumsum(rng.uniform(0.8, 1.2, n) / rate_hz)
    return times[times < t1]


def simulate_phone(world: World, route: list[Waypoint] | tuple[Waypoint, ...], seed: int, *,
                   wifi_hz: float = 1.0, ble_hz: float = 2.0, gait: Gait | None = None,
                   imu_params: ImuParams | None = None, radio: RadioModel | None = None) -> PhoneTrace:
    """Walk ``route`` and record what the phone measures; fully determined by ``seed``."""
    rng = np.random.default_rng([world.seed, seed])
    gait = gait or Gait.random(rng)
    walk = walk_route(route, gait, rng)
    imu = synthesize_imu(walk, rng, imu_params, north_deg=world.magnetic_north_deg, field_seed=world.seed)
    steps, headings = run_pdr(imu, PdrConfig(north_deg=world.magnetic_north_deg))
    radio = radio or RadioModel(world)
    scans: list[Scan] = []
    for kind, rate in (("wifi", wifi_hz), ("ble", ble_hz)):
        for t in scan_times(walk.t_start, walk.t_end, rate, rng):
            x, y, floor, heading = walk.pose_at(t)
            rss = radio.scan(x, y, floor, heading, kind, rng)
            if rss:
                scans.append({"t": round(float(t), 3), "rss": rss,
                              "heading_deg": round(float(heading_at(imu.t, headings, np.array([t]))[0]), 2)})
    scans.sort(key=lambda s: s["t"])
    return PhoneTrace(walk, steps, scans)
