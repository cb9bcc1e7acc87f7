"""Raw phone IMU synthesised from a walk's gait.

The phone is held flat in front of the walker, screen up, top pointing forward, so
its frame is x = right, y = forward, z = up (Android axes). Signals:

* accelerometer (m/s², specific force: +g on z at rest): per step a vertical
  oscillation ``−A·cos(2πφ)`` peaking mid-step, with ``A`` set so that the Weinberg
  quantity ``a_max − a_min = 2A`` equals ``(L / k_true)^4`` for that step's length L
  (a person-specific ``k_true``), a sharp heel-strike impact, forward surge, lateral
  sway at half the cadence, and white noise;
* gyroscope (rad/s): the yaw rate of the walk (counter-clockwise about z, i.e. the
  negative of the clockwise heading rate), gait wobble on x/y, a bias that drifts as
  a random walk, and white noise;
* magnetometer (µT): the earth field (north = ``world.magnetic_north_deg``) plus an
  indoor disturbance field that varies in space (a seeded random field, per floor),
  and noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .walker import Walk

GRAVITY = 9.80665
EARTH_H_UT = 20.0  # horizontal component of the earth field
EARTH_V_UT = 40.0  # vertical component (pointing down)


@dataclass(frozen=True)
class ImuParams:
    rate_hz: float = 100.0
    weinberg_k: float = 0.45  # the person's true Weinberg constant
    acc_noise: float = 0.15  # m/s² per sample
    impact_gain: float = 0.4  # heel-strike spike, relative to A
    gyro_noise_dps: float = 0.5
    gyro_bias_dps: float = 0.3  # std of the initial bias
    gyro_bias_walk_dps: float = 0.01  # bias random walk per sqrt(s)
    mag_noise_ut: float = 0.5
    mag_disturbance_ut: float = 6.0  # std of the indoor disturbance field (0 = clean)
    mag_disturbance_corr_m: float = 2.0


@dataclass
class ImuData:
    t: np.ndarray  # (N,) s
    acc: np.ndarray  # (N, 3) m/s²
    gyro: np.ndarray  # (N, 3) rad/s
    mag: np.ndarray  # (N, 3) µT


class MagneticField:
    """Earth field plus a seeded, spatially smooth indoor disturbance (site frame, µT)."""

    def __init__(self, north_deg: float, disturbance_ut: float, corr_m: float, seed: int, n_features: int = 32):
        n = math.radians(north_deg)
        self.earth = np.array([EARTH_H_UT * math.sin(n), EARTH_H_UT * math.cos(n), -EARTH_V_UT])
        rng = np.random.default_rng([seed, 0x3A6])
        self.k = rng.normal(0, 1 / corr_m, size=(8, 3, n_features, 2))  # 8 floors max
        self.phase = rng.uniform(0, 2 * math.pi, size=(8, 3, n_features))
        self.amp = disturbance_ut * math.sqrt(2 / n_features)

    def at(self, xy: np.ndarray, floor: np.ndarray) -> np.ndarray:
        """Field vectors (N, 3) at positions (N, 2) on floors (N,)."""
        out = np.tile(self.earth, (len(xy), 1))
        if self.amp == 0:
            return out
        fl = np.asarray(floor) % 8
        for axis in range(3):
            arg = np.einsum("nfd,nd->nf", self.k[fl, axis], xy) + self.phase[fl, axis]
            out[:, axis] += self.amp * np.cos(arg).sum(axis=1)
        return out


def synthesize_imu(walk: Walk, rng: np.random.Generator, params: ImuParams | None = None,
                   north_deg: float = 0.0, field_seed: int = 0) -> ImuData:
    """Accelerometer, gyroscope and magnetometer samples for the whole walk."""
    p = params or ImuParams()
    t = np.arange(walk.t_start, walk.t_end, 1.0 / p.rate_hz)
    n = len(t)
    i = np.searchsorted(walk.t, t, side="right")
    walking = (i > 0) & (i <= walk.n_steps)
    ii = np.clip(i, 1, walk.n_steps)
    dur = walk.t[ii] - walk.t[ii - 1]
    phase = np.where(walking, (t - walk.t[ii - 1]) / dur, 0.0)
    amp = np.where(walking, 0.5 * (walk.length_m[ii] / p.weinberg_k) ** 4, 0.0)

    a_v = -amp * np.cos(2 * math.pi * phase)
    a_v += p.impact_gain * amp * np.exp(-0.5 * ((phase - 0.05) * dur / 0.02) ** 2) * walking
    a_f = 0.3 * amp * np.sin(2 * math.pi * phase)
    a_l = 0.2 * amp * np.sin(math.pi * (ii + phase)) * walking
    acc = np.column_stack([a_l, a_f, GRAVITY + a_v]) + rng.normal(0, p.acc_noise, (n, 3))

    yaw_rate = -np.radians(walk.heading_rate_dps(t))
    bias0 = rng.normal(0, math.radians(p.gyro_bias_dps), 3)
    bias_walk = np.cumsum(rng.normal(0, math.radians(p.gyro_bias_walk_dps) / math.sqrt(p.rate_hz), (n, 3)), axis=0)
    wobble = np.radians(5.0) * np.column_stack([np.sin(2 * math.pi * phase), np.cos(math.pi * (ii + phase)), 0 * t])
    gyro = np.column_stack([0 * t, 0 * t, yaw_rate]) + wobble * walking[:, None] + bias0 + bias_walk
    gyro += rng.normal(0, math.radians(p.gyro_noise_dps), (n, 3))

    poses = [walk.pose_at(tt) for tt in t]
    xy = np.array([[q[0], q[1]] for q in poses])
    floor = np.array([q[2] for q in poses])
    h = np.radians([q[3] for q in poses])
    field = MagneticField(north_deg, p.mag_disturbance_ut, p.mag_disturbance_corr_m, field_seed).at(xy, floor)
    right = np.column_stack([np.cos(h), -np.sin(h)])
    fwd = np.column_stack([np.sin(h), np.cos(h)])
    mag = np.column_stack([(field[:, :2] * right).sum(1), (field[:, :2] * fwd).sum(1), field[:, 2]])
    mag += rng.normal(0, p.mag_noise_ut, (n, 3))
    return ImuData(t, acc, gyro, mag)
