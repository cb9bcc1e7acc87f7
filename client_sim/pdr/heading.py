"""Heading (degrees clockwise from the site's +y) from gyroscope, magnetometer, accelerometer.

* :class:`GyroMagKalman` — a 2-state Kalman filter ``[heading, gyro z bias]``: the
  integrated gyroscope predicts, the tilt-compensated magnetometer heading corrects.
  Magnetometer readings whose field strength is off the expected one, or whose
  innovation is implausible, are rejected (indoor disturbances near steel).
* :class:`QuasiStaticHeading` — the tilt-compensated gyroscope carries the heading; the
  magnetometer only corrects its offset, and only where the field looks undisturbed
  (strength and dip close to the site's, direction steady against the gyro over 1 s:
  "quasi-static field", Afzal et al. 2011). On the MSFT walks indoor fields are biased
  over tens of metres (the compass drifts 30–60° against the gyro within one walk); this
  beat the Kalman on the walks it was chosen on but not on held-out ones, where one
  disturbed but plausible start locks a wrong offset (docs/client-sim.md): an option.
* :class:`GyroHeading` — the same gyroscope heading, aligned once by the compass over the
  first second and never corrected after: its offset stays nearly constant over a walk,
  which the self-calibrating trackers learn (``client_sim msft``'s default, docs/client-sim.md).
* :class:`QuaternionEKF` — attitude quaternion predicted by the gyroscope and
  corrected by the accelerometer's gravity direction (tilt); yaw comes from the
  gyroscope alone after the initial alignment, so it is the drift baseline.

Phone axes are Android's (x right, y top, z out of the screen); "heading" is the
direction the phone's top points, projected on the floor.
"""

from __future__ import annotations

import math

import numpy as np

from ..imu import ImuData


def _moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or len(x) < n:
        return x
    k = np.ones(n) / n
    return np.column_stack([np.convolve(x[:, i], k, mode="same") for i in range(x.shape[1])])


def mag_heading_deg(acc: np.ndarray, mag: np.ndarray, north_deg: float = 0.0) -> np.ndarray:
    """Tilt-compensated compass heading of the phone's y axis (per sample)."""
    up = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    east = np.cross(mag, up)
    north = np.cross(up, east)
    return (np.degrees(np.arctan2(east[:, 1], north[:, 1])) + north_deg) % 360.0


def is_still(gyro: np.ndarray, acc: np.ndarray, gyro_std_rad_s: float = 0.05, acc_std: float = 0.3) -> bool:
    """Whether a window of samples looks like a phone at rest (no turning, no gait)."""
    if len(gyro) < 10:
        return False
    return bool(gyro.std(axis=0).max() < gyro_std_rad_s and np.linalg.norm(acc, axis=1).std() < acc_std)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class GyroMagKalman:
    """Kalman filter on ``[heading (rad, clockwise), gyro z bias (rad/s)]``."""

    def __init__(self, gyro_noise_dps: float = 0.5, bias_walk_dps: float = 0.02, mag_std_deg: float = 20.0,
                 gate_deg: float = 45.0, field_tolerance_ut: float = 8.0, expected_field_ut: float | None = None):
        self.q_gyro = math.radians(gyro_noise_dps) ** 2
        self.q_bias = math.radians(bias_walk_dps) ** 2
        self.r_mag = math.radians(mag_std_deg) ** 2
        self.gate = math.radians(gate_deg)
        self.field_tol = field_tolerance_ut
        self.expected_field = expected_field_ut

    def run(self, imu: ImuData, north_deg: float = 0.0, initial_heading_deg: float | None = None,
            stand_s: float = 1.0) -> np.ndarray:
        """Heading (deg) at every IMU sample."""
        t, gyro = imu.t, imu.gyro
        rate = 1.0 / np.median(np.diff(t))
        acc_s = _moving_mean(imu.acc, int(rate))  # gravity direction, gait averaged out
        compass = np.radians(mag_heading_deg(acc_s, imu.mag, north_deg))
        strength = np.linalg.norm(imu.mag, axis=1)
        start = t < t[0] + stand_s
        # Initial alignment: mean compass over the first stand_s; the gyro bias and the
        # expected field strength are taken from that window only if the phone really
        # stood still there. A recording that starts mid-walk (real phones) would
        # otherwise turn a turn-rate into a "bias" of several °/s and an odd local
        # field into the expected one, after which every compass reading is rejected.
        still = start if is_still(gyro[start], imu.acc[start]) else np.zeros_like(start)
        expected = self.expected_field or float(np.median(strength[still] if still.any() else strength))
        if initial_heading_deg is not None:
            h = math.radians(initial_heading_deg)
        else:
            c = compass[start] if start.any() else compass[:1]
            h = math.atan2(np.sin(c).mean(), np.cos(c).mean())
        b = float(gyro[still, 2].mean()) if still.sum() > 10 else 0.0
        P = np.diag([math.radians(5.0) ** 2, math.radians(0.1) ** 2])
        out = np.empty(len(t))
        out[0] = h
        for k in range(1, len(t)):
            dt = t[k] - t[k - 1]
            # the gyro measures counter-clockwise yaw rate; heading is clockwise
            h = h - (gyro[k, 2] - b) * dt
            F = np.array([[1.0, dt], [0.0, 1.0]])
            P = F @ P @ F.T + np.diag([self.q_gyro * dt * dt * rate, self.q_bias * dt])
            if abs(strength[k] - expected) < self.field_tol:
                innov = _wrap(compass[k] - h)
                S = P[0, 0] + self.r_mag * rate / 10.0  # ~10 independent readings per second
                if innov * innov < (self.gate ** 2) + 9 * S:
                    K = P[:, 0] / S
                    h += K[0] * innov
                    b += K[1] * innov
                    P = P - np.outer(K, P[0, :])
            out[k] = h
        return np.degrees(out) % 360.0


def gravity_up(acc: np.ndarray, rate_hz: float) -> np.ndarray:
    """Unit "up" vector per sample in phone axes: the accelerometer averaged over 1 s."""
    up = _moving_mean(acc, int(rate_hz))
    return up / np.linalg.norm(up, axis=1, keepdims=True)


def field_strength_dip(mag: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: the magnetic field's strength (µT) and dip below the horizon (deg)."""
    strength = np.linalg.norm(mag, axis=1)
    return strength, np.degrees(np.arcsin(np.clip(-(mag * up).sum(axis=1) / strength, -1.0, 1.0)))


class QuasiStaticHeading:
    """Gyro heading plus a magnetometer-estimated offset, corrected in quasi-static field only.

    The heading is ``g(t) + c``: ``g`` integrates the gyroscope's rate about gravity
    (tilt-compensated, so a tilted phone turns 90° when the walker does), and ``c``, the
    offset to magnetic north, is a one-state Kalman filter (random walk ``q_dps`` °/√s)
    updated at ``update_hz`` by ``compass − g`` where the field is quasi-static: its
    strength within ``field_tolerance_ut`` and its dip within ``dip_tolerance_deg`` of the
    site's, and ``compass − g`` steady (circular std < ``steady_deg``) over ``window_s``.
    The defaults were chosen on MSFT site-1 folds 0–1 (docs/client-sim.md).
    """

    def __init__(self, q_dps: float = 0.1, mag_std_deg: float = 20.0, initial_std_deg: float = 20.0,
                 field_tolerance_ut: float = 8.0, dip_tolerance_deg: float = 10.0, steady_deg: float = 3.0,
                 window_s: float = 1.0, update_hz: float = 10.0):
        self.q = math.radians(q_dps) ** 2
        self.r = math.radians(mag_std_deg) ** 2
        self.p0 = math.radians(initial_std_deg) ** 2
        self.field_tol, self.dip_tol, self.steady = field_tolerance_ut, dip_tolerance_deg, steady_deg
        self.window_s, self.update_hz = window_s, update_hz

    def quasi_static(self, t: np.ndarray, offset: np.ndarray, mag: np.ndarray, up: np.ndarray,
                     field_ut: float | None, dip_deg: float | None) -> np.ndarray:
        """Samples where the compass may correct the offset (trailing window, causal);
        ``field_ut``/``dip_deg`` None: this recording's median."""
        strength, dip = field_strength_dip(mag, up)
        field_ut = float(np.median(strength)) if field_ut is None else field_ut
        dip_deg = float(np.median(dip)) if dip_deg is None else dip_deg
        n = max(2, int(self.window_s / np.median(np.diff(t))))
        csum = np.concatenate([[0], np.cumsum(np.exp(1j * offset))])
        idx = np.arange(len(t))
        lo = np.maximum(idx + 1 - n, 0)
        resultant = np.abs(csum[idx + 1] - csum[lo]) / (idx + 1 - lo)
        circ_std = np.degrees(np.sqrt(-2 * np.log(np.clip(resultant, 1e-9, 1.0))))
        return ((idx + 1 >= n) & (circ_std < self.steady) & (np.abs(strength - field_ut) < self.field_tol)
                & (np.abs(dip - dip_deg) < self.dip_tol))

    def run(self, imu: ImuData, north_deg: float = 0.0, initial_heading_deg: float | None = None,
            field_ut: float | None = None, dip_deg: float | None = None) -> np.ndarray:
        """Heading (deg) at every IMU sample. ``field_ut``/``dip_deg``: the site's undisturbed
        field (from its map walks); ``None`` takes this recording's median (offline only)."""
        t = imu.t
        rate = 1.0 / float(np.median(np.diff(t)))
        up = gravity_up(imu.acc, rate)
        # the gyro measures counter-clockwise rate; heading is clockwise
        g = np.cumsum(-(imu.gyro * up).sum(axis=1) * np.diff(t, prepend=t[0]))
        compass = np.radians(mag_heading_deg(up, imu.mag, north_deg))
        offset = np.angle(np.exp(1j * (compass - g)))
        ok = self.quasi_static(t, offset, imu.mag, up, field_ut, dip_deg)
        if initial_heading_deg is not None:
            c, P = math.radians(initial_heading_deg), math.radians(5.0) ** 2
        else:  # the compass over the first second, whatever the field there
            first = offset[t < t[0] + 1.0]
            c, P = math.atan2(np.sin(first).mean(), np.cos(first).mean()), self.p0
        every = max(1, int(round(rate / self.update_hz)))
        cs = np.empty(len(t))
        done, last = 0, t[0]
        for k in np.flatnonzero(ok & (np.arange(len(t)) % every == 0)):
            cs[done:k] = c
            done = int(k)
            P += self.q * (t[k] - last)
            last = t[k]
            gain = P / (P + self.r)
            c += gain * _wrap(offset[k] - c)
            P -= gain * P
        cs[done:] = c
        return np.degrees(g + cs) % 360.0


class GyroHeading(QuasiStaticHeading):
    """The tilt-compensated gyro, aligned once by the compass over its first second and never
    corrected after (``QuasiStaticHeading`` with no quasi-static samples).

    On the MSFT walks the compass swings 30–60° within a walk indoors, while the gyro's offset
    stays nearly constant over one: a constant offset is what the self-calibrating trackers
    learn as their heading bias, a wandering one is not (docs/client-sim.md)."""

    def quasi_static(self, t: np.ndarray, offset: np.ndarray, mag: np.ndarray, up: np.ndarray,
                     field_ut: float | None, dip_deg: float | None) -> np.ndarray:
        return np.zeros(len(t), dtype=bool)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix body → site of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


class QuaternionEKF:
    """EKF on the attitude quaternion: gyro prediction, accelerometer (gravity) update."""

    def __init__(self, gyro_noise_dps: float = 0.5, acc_std: float = 2.0):
        self.q_gyro = math.radians(gyro_noise_dps) ** 2
        self.r_acc = acc_std ** 2

    @staticmethod
    def _gravity_body(q: np.ndarray) -> np.ndarray:
        return _rot(q).T @ np.array([0.0, 0.0, 1.0])

    def run(self, imu: ImuData, initial_heading_deg: float = 0.0, stand_s: float = 1.0) -> np.ndarray:
        t, gyro, acc = imu.t, imu.gyro, imu.acc
        still = t < t[0] + stand_s
        bias = gyro[still].mean(axis=0) if still.sum() > 10 else np.zeros(3)
        # yaw about site z: heading h clockwise means rotation by −h counter-clockwise
        half = -math.radians(initial_heading_deg) / 2
        q = np.array([math.cos(half), 0.0, 0.0, math.sin(half)])
        P = np.eye(4) * 1e-4
        out = np.empty(len(t))
        for k in range(len(t)):
            if k:
                dt = t[k] - t[k - 1]
                w = (gyro[k] - bias) * dt
                dq = np.array([1.0, *(0.5 * w)])
                omega = np.array([[0, -w[0], -w[1], -w[2]], [w[0], 0, w[2], -w[1]],
                                  [w[1], -w[2], 0, w[0]], [w[2], w[1], -w[0], 0]])
                q = _quat_mul(q, dq)
                q /= np.linalg.norm(q)
                F = np.eye(4) + 0.5 * omega  # q ⊗ dq = (I + Ω/2) q
                P = F @ P @ F.T + np.eye(4) * self.q_gyro * dt * dt / 4
                a = acc[k] / np.linalg.norm(acc[k])
                h0 = self._gravity_body(q)
                H = np.empty((3, 4))
                for j in range(4):  # numeric Jacobian: 4 cheap evaluations
                    dqj = np.zeros(4)
                    dqj[j] = 1e-6
                    H[:, j] = (self._gravity_body(q + dqj) - h0) / 1e-6
                S = H @ P @ H.T + np.eye(3) * self.r_acc / 96.0  # normalised acc: std /g
                K = P @ H.T @ np.linalg.inv(S)
                q = q + K @ (a - h0)
                q /= np.linalg.norm(q)
                P = (np.eye(4) - K @ H) @ P
            fwd = _rot(q) @ np.array([0.0, 1.0, 0.0])
            out[k] = math.degrees(math.atan2(fwd[0], fwd[1])) % 360.0
        return out
