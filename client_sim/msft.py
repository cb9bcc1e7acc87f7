"""Microsoft Indoor Location Competition 2.0 walk files: reader, truth, PDR and scans.

One walk is one tab-separated text file, lines ``time_ms  TYPE_...  values`` (header
lines start with ``#``). What is read here:

* ``TYPE_ACCELEROMETER`` / ``TYPE_GYROSCOPE`` / ``TYPE_MAGNETIC_FIELD`` /
  ``TYPE_ROTATION_VECTOR`` (≈50 Hz, Android axes and units: m/s², rad/s, µT);
* ``TYPE_WIFI``: ssid, bssid, rssi, frequency, last-seen time (ms). All lines with
  the same ``time_ms`` are one scan result. Android hands back cached entries, so a
  scan carries access points last seen many seconds earlier; :func:`wifi_scans`
  keeps only entries seen within ``max_age_s`` of the scan and never re-uses an
  (bssid, last-seen) observation that an earlier scan already reported;
* ``TYPE_BEACON``: uuid, major, minor, tx power, rssi, distance, mac;
* ``TYPE_WAYPOINT``: x, y (metres, floor-plan frame: x east, y north).

Other line types (uncalibrated sensors, ``TYPE_BLUE``…) are skipped.

Transmitter ids follow API.md: ``wifi:<bssid lower-case>``; an iBeacon is
``ble:<uuid lower>:<major>:<minor>``, except that on this site most beacons share
one uuid with major = minor = 0 — a placeholder that names no beacon — so those are
told apart by their MAC, as a data-set name: ``ble:<mac hex, lower, no colons>``.

Time: the walk's ``time_ms`` clock, in seconds (``t`` fields in the API may use any
epoch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np

from .batches import Scan
from .consistency import squared_mahalanobis
from .imu import ImuData
from .pdr import PdrConfig, PdrStep, heading_at, heading_track
from .pdr.heading import field_strength_dip, gravity_up
from .pdr.step_detection import find_step_peaks
from .pdr.step_length import weinberg


# --------------------------------------------------------------------------- reading
@dataclass
class WifiReading:
    t: float  # scan result time (s)
    bssid: str
    rssi: float
    last_seen: float  # s


@dataclass
class BeaconReading:
    t: float
    tx_id: str
    rssi: float


@dataclass
class Walk:
    name: str
    acc: np.ndarray  # (N, 4): t, x, y, z
    gyro: np.ndarray
    mag: np.ndarray
    rotvec: np.ndarray  # (N, 4): t, x, y, z (the vector part; w is implied)
    wifi: list[WifiReading] = field(default_factory=list)
    beacons: list[BeaconReading] = field(default_factory=list)
    waypoints: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))  # (M, 3): t, x, y

    @property
    def t_start(self) -> float:
        return float(self.waypoints[0, 0])

    @property
    def t_end(self) -> float:
        return float(self.waypoints[-1, 0])

    def truth_at(self, t) -> np.ndarray:
        """Position(s) linearly interpolated between the waypoints around ``t``."""
        return interpolate_waypoints(self.waypoints, t)

    def imu(self) -> ImuData:
        """Accelerometer, gyroscope and magnetometer on the accelerometer's time grid."""
        return imu_from_arrays(self.acc, self.gyro, self.mag)


def beacon_id(uuid: str, major: str, minor: str, mac: str) -> str:
    if int(major) == 0 and int(minor) == 0:
        return "ble:" + mac.replace(":", "").lower()
    return f"ble:{uuid.lower()}:{int(major)}:{int(minor)}"


def read_walk(path: str | Path) -> Walk:
    """Parse one walk file (see the module doc for what is kept)."""
    path = Path(path)
    acc, gyro, mag, rot, wps = [], [], [], [], []
    wifi: list[WifiReading] = []
    beacons: list[BeaconReading] = []
    with path.open(encoding="utf-8", errors="replace") as f:
        for line in f:
            if not line or line[0] == "#":
                continue
            parts = line.rstrip("\r\n").split("\t")
            if len(parts) < 3:
                continue
            kind = parts[1]
            try:
                t = int(parts[0]) / 1000.0
                if kind == "TYPE_ACCELEROMETER":
                    acc.append((t, float(parts[2]), float(parts[3]), float(parts[4])))
                elif kind == "TYPE_GYROSCOPE":
                    gyro.append((t, float(parts[2]), float(parts[3]), float(parts[4])))
                elif kind == "TYPE_MAGNETIC_FIELD":
                    mag.append((t, float(parts[2]), float(parts[3]), float(parts[4])))
                elif kind == "TYPE_ROTATION_VECTOR":
                    rot.append((t, float(parts[2]), float(parts[3]), float(parts[4])))
                elif kind == "TYPE_WAYPOINT":
                    wps.append((t, float(parts[2]), float(parts[3])))
                elif kind == "TYPE_WIFI":
                    # ssid may be empty; bssid, rssi, frequency, last-seen are the last four
                    bssid, rssi, last_seen = parts[-4], float(parts[-3]), int(parts[-1]) / 1000.0
                    wifi.append(WifiReading(t, bssid.lower(), rssi, last_seen))
                elif kind == "TYPE_BEACON":
                    uuid, major, minor = parts[2], parts[3], parts[4]
                    rssi, mac = float(parts[6]), parts[8]
                    beacons.append(BeaconReading(t, beacon_id(uuid, major, minor, mac), rssi))
            except (ValueError, IndexError):
                continue  # a truncated or malformed line: skip it, as a phone app would
    arr = lambda rows, n: np.array(rows, dtype=float).reshape(-1, n)  # noqa: E731
    w = arr(wps, 3)
    w = w[np.argsort(w[:, 0], kind="stable")]
    return Walk(path.stem, arr(acc, 4), arr(gyro, 4), arr(mag, 4), arr(rot, 4), wifi, beacons, w)


def imu_from_arrays(acc: np.ndarray, gyro: np.ndarray, mag: np.ndarray) -> ImuData:
    """One time base (the accelerometer's) for the three sensors, by linear interpolation."""
    t = acc[:, 0]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, a = t[keep], acc[keep, 1:]

    def on_t(x: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, x[:, 0], x[:, i]) for i in (1, 2, 3)])

    return ImuData(t, a, on_t(gyro), on_t(mag))


def interpolate_waypoints(waypoints: np.ndarray, t) -> np.ndarray:
    """Linear interpolation of (t, x, y) waypoints; clamps outside their span."""
    t = np.asarray(t, dtype=float)
    x = np.interp(t, waypoints[:, 0], waypoints[:, 1])
    y = np.interp(t, waypoints[:, 0], waypoints[:, 2])
    return np.stack([x, y], axis=-1)


# --------------------------------------------------------------------------- scans
def wifi_scans(walk: Walk, max_age_s: float = 3.0) -> list[Scan]:
    """WiFi scan results as API scans ``{t, rss}``, stale entries removed.

    An entry is kept when its last-seen time is within ``max_age_s`` before the scan
    result (and not after it by more than 1 s of clock skew), and when the same
    ``(bssid, last-seen)`` observation was not already reported by an earlier scan.
    Within one scan a bssid listed twice keeps its most recent reading. ``t`` is the
    median last-seen time of the kept entries (when the radio actually heard them),
    scans are sorted by it, and a scan left empty is dropped.
    """
    by_time: dict[float, list[WifiReading]] = {}
    for r in walk.wifi:
        by_time.setdefault(r.t, []).append(r)
    seen: set[tuple[str, float]] = set()
    scans: list[Scan] = []
    for t in sorted(by_time):
        best: dict[str, WifiReading] = {}
        for r in by_time[t]:
            age = t - r.last_seen
            if age > max_age_s or age < -1.0 or (r.bssid, r.last_seen) in seen:
                continue
            if r.bssid not in best or r.last_seen > best[r.bssid].last_seen:
                best[r.bssid] = r
        seen.update((r.bssid, r.last_seen) for r in by_time[t])
        if best:
            t_heard = float(np.median([r.last_seen for r in best.values()]))
            scans.append({"t": round(t_heard, 3),
                          "rss": {f"wifi:{b}": float(r.rssi) for b, r in sorted(best.items())}})
    scans.sort(key=lambda s: s["t"])
    return scans


def beacon_scans(walk: Walk, window_s: float = 1.0) -> list[Scan]:
    """iBeacon readings grouped into windows of ``window_s`` (strongest reading per
    beacon in a window); the scan's ``t`` is the window's last reading."""
    scans: list[Scan] = []
    if not walk.beacons:
        return scans
    readings = sorted(walk.beacons, key=lambda r: r.t)
    start = readings[0].t
    cur: dict[str, float] = {}
    last = start
    for r in readings:
        if r.t >= start + window_s:
            if cur:
                scans.append({"t": round(last, 3), "rss": dict(sorted(cur.items()))})
            start = start + window_s * math.floor((r.t - start) / window_s)
            cur = {}
        cur[r.tx_id] = max(cur.get(r.tx_id, -math.inf), r.rssi)
        last = r.t
    if cur:
        scans.append({"t": round(last, 3), "rss": dict(sorted(cur.items()))})
    return scans


def survey_rows(walk: Walk, scans: list[Scan], floor: int = 0, device: str | None = None) -> list[dict]:
    """API survey fingerprints: each scan placed at the waypoint-interpolated position
    of its time; scans outside the waypoints' time span are left out (no truth there)."""
    rows = []
    for s in scans:
        if not walk.t_start <= s["t"] <= walk.t_end:
            continue
        x, y = walk.truth_at(s["t"])
        row = {"x": round(float(x), 3), "y": round(float(y), 3), "floor": floor, "rss": s["rss"], "t": s["t"]}
        if device:
            row["device"] = device
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- PDR
@dataclass(frozen=True)
class UncalibratedSteps:
    """Steps as the phone detects them, before the site calibration sets their length and
    heading offset: step times, the Weinberg swing ``a_max − a_min`` per step, and the raw
    filter heading at each step (degrees clockwise from magnetic north as the phone sees it)."""

    t: np.ndarray
    swing: np.ndarray
    heading_deg: np.ndarray


def field_reference(walks: list[Walk]) -> tuple[float, float]:
    """The site's undisturbed magnetic field as its phones measure it: the median strength
    (µT) and dip (deg, down positive) over every sample of ``walks`` (the map walks). Most
    of a floor is only mildly disturbed, so the medians are the earth field there (site 1:
    43 µT, 45°, the same to 0.4 µT and 0.9° in every fold)."""
    strength, dip = [], []
    for w in walks:
        imu = w.imu()
        b, d = field_strength_dip(imu.mag, gravity_up(imu.acc, 1.0 / float(np.median(np.diff(imu.t)))))
        strength.append(b)
        dip.append(d)
    return float(np.median(np.concatenate(strength))), float(np.median(np.concatenate(dip)))


def detect_steps(walk: Walk, config: PdrConfig | None = None) -> UncalibratedSteps:
    """Run the project's on-phone PDR (peak detector + the config's heading filter) on the
    walk's raw IMU. Headings are magnetic (``north_deg`` of the config)."""
    cfg = config or PdrConfig()
    imu = walk.imu()
    ev = find_step_peaks(imu.t, imu.acc, cfg.detector)
    headings = heading_track(imu, cfg)
    return UncalibratedSteps(ev.t, np.maximum(ev.a_max - ev.a_min, 0.0), heading_at(imu.t, headings, ev.t))


def steps_from_events(ev: UncalibratedSteps, weinberg_k: float, heading_offset_deg: float,
                      length_std_m: float | None = 0.1, heading_std_deg: float | None = 8.0) -> list[PdrStep]:
    """Steps in the site frame: Weinberg length with ``weinberg_k``, heading + offset; std fields of
    None are not sent."""
    lengths = weinberg(ev.swing, np.zeros_like(ev.swing), weinberg_k)
    heads = (ev.heading_deg + heading_offset_deg) % 360.0
    return [PdrStep(float(t), float(length), float(h), length_std_m, heading_std_deg)
            for t, length, h in zip(ev.t, lengths, heads, strict=True)]


def dead_reckon(steps: list[PdrStep], start_xy, t0: float) -> np.ndarray:
    """PDR-only track ``(t, x, y)`` from ``start_xy`` at ``t0`` (steps before t0 ignored)."""
    x, y = float(start_xy[0]), float(start_xy[1])
    out = [(t0, x, y)]
    for s in steps:
        if s.t <= t0:
            continue
        h = math.radians(s.heading_deg)
        x += s.length_m * math.sin(h)
        y += s.length_m * math.cos(h)
        out.append((s.t, x, y))
    return np.array(out)


def segment_displacements(ev: UncalibratedSteps, waypoints: np.ndarray, weinberg_k: float = 1.0,
                          t_until: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per waypoint segment (ending at or before ``t_until``): the PDR displacement of
    the steps inside it (magnetic headings, lengths with ``weinberg_k``) and the true
    displacement. Both ``(S, 2)`` arrays in (east, north)-like components."""
    lengths = weinberg(ev.swing, np.zeros_like(ev.swing), weinberg_k)
    h = np.radians(ev.heading_deg)
    dx, dy = lengths * np.sin(h), lengths * np.cos(h)
    pdr, true = [], []
    for (t0, x0, y0), (t1, x1, y1) in pairwise(waypoints):
        if t_until is not None and t1 > t_until + 1e-9:
            break
        m = (ev.t > t0) & (ev.t <= t1)
        pdr.append((dx[m].sum(), dy[m].sum()))
        true.append((x1 - x0, y1 - y0))
    return np.array(pdr).reshape(-1, 2), np.array(true).reshape(-1, 2)


def fit_rotation_scale(pdr: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """The clockwise heading offset (deg) and length scale that best map PDR
    displacements onto true ones (least squares over the summed vectors:
    ``offset = atan2(Σ cross, Σ dot)``, ``scale = Σ|true| / Σ|pdr|``).

    With heading clockwise from +y, rotating a displacement (dx, dy) by a heading
    offset δ gives (dx cos δ + dy sin δ, −dx sin δ + dy cos δ).
    """
    if len(pdr) == 0:
        raise ValueError("no segment to calibrate on")
    # clockwise offset: true ≈ R(−δ) pdr in the usual counter-clockwise convention
    dot = float((pdr * true).sum())
    cross = float((pdr[:, 1] * true[:, 0] - pdr[:, 0] * true[:, 1]).sum())
    offset = math.degrees(math.atan2(cross, dot)) % 360.0
    norm_p = float(np.linalg.norm(pdr, axis=1).sum())
    scale = float(np.linalg.norm(true, axis=1).sum()) / norm_p if norm_p > 0 else 1.0
    return offset, scale


def calibration_window(waypoints: np.ndarray, min_distance_m: float = 10.0, min_segments: int = 1) -> float:
    """End time of the first waypoint segments that together cover ``min_distance_m``
    (at least ``min_segments`` of them, never the whole walk if it has more than
    one segment): the part of a walk an app would use for its initial alignment."""
    n = len(waypoints) - 1
    if n < 1:
        raise ValueError("fewer than two waypoints")
    dist = 0.0
    for i in range(n):
        dist += math.dist(waypoints[i, 1:], waypoints[i + 1, 1:])
        if i + 1 >= min_segments and dist >= min_distance_m:
            return float(waypoints[i + 1, 0])
        if i + 1 == n - 1 and n > 1:  # keep the last segment out of the calibration
            return float(waypoints[i + 1, 0])
    return float(waypoints[-1, 0])


# --------------------------------------------------------------------------- errors
def errors_against(walk: Walk, track) -> list[dict]:
    """Rows ``{t, x, y, error_m}`` for estimates ``(t, x, y)`` inside the waypoints' time span;
    an estimate ``(t, x, y, covariance)`` also gets ``nees``, its squared Mahalanobis distance
    from the truth (2 on average when the covariance is honest)."""
    rows = []
    for t, x, y, *cov in track:
        if not walk.t_start <= t <= walk.t_end:
            continue
        tx, ty = walk.truth_at(t)
        row = {"t": round(float(t), 3), "x": round(float(x), 3), "y": round(float(y), 3),
               "error_m": round(math.hypot(x - tx, y - ty), 3)}
        if cov:
            row["nees"] = round(squared_mahalanobis(x - tx, y - ty, cov[0]), 3)
        rows.append(row)
    return rows


def consistency(rows) -> dict:
    """Mean and median NEES of rows that have one (empty when none has)."""
    v = np.asarray([r["nees"] for r in rows if "nees" in r], dtype=float)
    if len(v) == 0:
        return {}
    return {"nees_mean": round(float(v.mean()), 2), "nees_p50": round(float(np.median(v)), 2)}


def summarise(errors) -> dict:
    e = np.asarray(list(errors), dtype=float)
    if len(e) == 0:
        return {"n": 0, "mean": None, "p50": None, "p90": None, "max": None}
    return {"n": int(len(e)), "mean": round(float(e.mean()), 2), "p50": round(float(np.percentile(e, 50)), 2),
            "p90": round(float(np.percentile(e, 90)), 2), "max": round(float(e.max()), 2)}
