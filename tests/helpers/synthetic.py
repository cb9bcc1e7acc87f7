"""A small synthetic site for tests and benchmarks: path-loss radio, a grid of reference
points on several floors, WiFi and BLE transmitters, optional body shadowing.

RSS = R0 − 10·γ·log10(d) − floor_loss·|Δfloor| − body_loss·[transmitter behind the
walker] + N(0, noise²), d the 3-D distance (≥ 1 m); readings below ``sensitivity``
are not heard.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from server.estimation.fingerprint.dataset import FingerprintSet
from server.estimation.radio import rss_at


@dataclass
class SyntheticSite:
    transmitters: list[dict]  # API Transmitter dicts (with the true R0 and γ)
    rp: list[tuple[str, float, float, int]]  # (label, x, y, floor)
    floor_height_m: float = 4.0
    floor_loss_db: float = 15.0
    body_loss_db: float = 0.0
    noise_db: float = 2.0
    sensitivity_dbm: float = -100.0

    def scan(self, x: float, y: float, floor: int, heading_deg: float | None, rng: np.random.Generator,
             noise_db: float | None = None) -> dict[str, float]:
        noise = self.noise_db if noise_db is None else noise_db
        out = {}
        for t in self.transmitters:
            dx, dy = t["x"] - x, t["y"] - y
            dz = (t["floor"] - floor) * self.floor_height_m
            d = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1.0)
            rss = rss_at(d, t["tx_power_dbm"], t["path_loss_exponent"])
            rss -= self.floor_loss_db * abs(t["floor"] - floor)
            if heading_deg is not None and self.body_loss_db:
                h = math.radians(heading_deg)
                ahead = math.sin(h) * dx + math.cos(h) * dy  # component along the walking direction
                if ahead < 0:
                    rss -= self.body_loss_db
            rss += rng.normal(0, noise)
            if rss >= self.sensitivity_dbm:
                out[t["id"]] = float(min(rss, 0.0))
        return out

    def survey(self, scans_per_rp: int = 6, seed: int = 0, headings=(0.0, 90.0, 180.0, 270.0),
               devices=("a", "b", "c")) -> FingerprintSet:
        rng = np.random.default_rng(seed)
        rows = []
        for label, x, y, f in self.rp:
            for k in range(scans_per_rp):
                h = headings[k % len(headings)] if headings else None
                rows.append({"x": x, "y": y, "floor": f, "label": label, "heading_deg": h,
                             "device": devices[k % len(devices)], "rss": self.scan(x, y, f, h, rng)})
        return FingerprintSet.from_rows(rows, tx_ids=[t["id"] for t in self.transmitters])


def with_prefix(site, prefix: str):
    """``site`` with every transmitter id's name prefixed (``wifi:ap0`` → ``wifi:b1ap0``), so
    two synthetic buildings do not share transmitters; returns the same site."""
    for t in site.transmitters:
        kind, name = t["id"].split(":", 1)
        t["id"] = f"{kind}:{prefix}{name}"
    return site


def make_site(nx: int = 5, ny: int = 4, spacing_m: float = 3.0, floors=(0, 1), n_wifi: int = 6, n_ble: int = 6,
              seed: int = 0, **kw) -> SyntheticSite:
    """Transmitters spread over the floors' rectangle; reference points on a grid."""
    rng = np.random.default_rng(seed)
    w, h = (nx - 1) * spacing_m, (ny - 1) * spacing_m
    tx = []
    for kind, n, r0 in (("wifi", n_wifi, -40.0), ("ble", n_ble, -60.0)):
        for i in range(n):
            tx.append({
                "id": f"{kind}:{kind[0]}{i:02d}", "kind": kind, "floor": int(floors[i % len(floors)]),
                "x": float(rng.uniform(-2, w + 2)), "y": float(rng.uniform(-2, h + 2)),
                "tx_power_dbm": r0 + float(rng.uniform(-3, 3)), "path_loss_exponent": float(rng.uniform(2.0, 3.0)),
            })
    rp = [(f"f{f}-x{i}-y{j}", i * spacing_m, j * spacing_m, int(f))
          for f in floors for i in range(nx) for j in range(ny)]
    return SyntheticSite(transmitters=tx, rp=rp, **kw)
