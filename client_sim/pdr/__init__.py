"""On-phone pedestrian dead reckoning: steps, their lengths and headings from raw IMU."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..imu import ImuData
from .heading import GyroHeading, GyroMagKalman, QuasiStaticHeading, QuaternionEKF
from .step_detection import PeakDetectorParams, find_step_peaks
from .step_length import DEFAULT_WEINBERG_K, weinberg


@dataclass(frozen=True)
class PdrStep:
    """One step as the phone reports it in a batch (API.md ``steps`` item)."""

    t: float
    length_m: float
    heading_deg: float
    #: the declared step noise; None: not sent (the server's defaults apply)
    length_std_m: float | None = 0.08
    heading_std_deg: float | None = 6.0

    def to_api(self) -> dict:
        out = {"t": round(self.t, 3), "length_m": round(self.length_m, 3), "heading_deg": round(self.heading_deg, 2)}
        if self.length_std_m is not None:
            out["length_std_m"] = self.length_std_m
        if self.heading_std_deg is not None:
            out["heading_std_deg"] = self.heading_std_deg
        return out


@dataclass(frozen=True)
class PdrConfig:
    weinberg_k: float = DEFAULT_WEINBERG_K
    #: "kalman" (gyro + magnetometer Kalman) | "quasi-static" (gyro, compass offset in undisturbed
    #: field only: :class:`QuasiStaticHeading`) | "gyro" (gyro aligned once by the compass:
    #: :class:`GyroHeading`) | "qekf" (gyro + accelerometer)
    heading: str = "kalman"
    north_deg: float = 0.0  # magnetic north in the site frame, known to the app from the site map
    #: the site's undisturbed field strength (µT) and dip (deg) for "quasi-static"; None = the recording's median
    field_ut: float | None = None
    dip_deg: float | None = None
    detector: PeakDetectorParams = PeakDetectorParams()


def heading_track(imu: ImuData, config: PdrConfig, initial_heading_deg: float | None = None) -> np.ndarray:
    """Heading (deg) at each IMU sample, by the configured filter."""
    if config.heading == "qekf":
        return QuaternionEKF().run(imu, initial_heading_deg=initial_heading_deg or 0.0)
    if config.heading == "gyro":
        return GyroHeading().run(imu, config.north_deg, initial_heading_deg)
    if config.heading == "quasi-static":
        return QuasiStaticHeading().run(imu, config.north_deg, initial_heading_deg, config.field_ut, config.dip_deg)
    return GyroMagKalman().run(imu, north_deg=config.north_deg, initial_heading_deg=initial_heading_deg)


def run_pdr(imu: ImuData, config: PdrConfig | None = None, initial_heading_deg: float | None = None
            ) -> tuple[list[PdrStep], np.ndarray]:
    """Steps detected in ``imu`` with Weinberg lengths and filtered headings.

    Returns the steps and the per-sample heading track (scans borrow their heading
    from it). A step's heading is the filter's heading at the step's acceleration
    peak, which is mid-stride.
    """
    cfg = config or PdrConfig()
    events = find_step_peaks(imu.t, imu.acc, cfg.detector)
    headings = heading_track(imu, cfg, initial_heading_deg)
    lengths = weinberg(events.a_max, events.a_min, cfg.weinberg_k)
    step_h = heading_at(imu.t, headings, events.t)
    steps = [PdrStep(float(t), float(length), float(h)) for t, length, h in zip(events.t, lengths, step_h, strict=True)]
    return steps, headings


def heading_at(t: np.ndarray, headings_deg: np.ndarray, when: np.ndarray) -> np.ndarray:
    """Interpolate a heading track at times ``when`` (unwrapped, so 359→1 stays sane)."""
    unwrapped = np.unwrap(np.radians(headings_deg))
    return np.degrees(np.interp(when, t, unwrapped)) % 360.0
