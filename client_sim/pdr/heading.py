"""Heading (degrees clockwise from the site's +y) from gyroscope, magnetometer, accelerometer.

* :class:`GyroMagKalman` — a 2-state Kalman filter ``[heading, gyro z bias]``: the
  integrated gyroscope predicts, the tilt-compensated magnetometer heading corrects.
  Magnetometer readings whose field strength is off the expected one, or whose
  innovation is implausible, are rejected (indoor disturbances near steel).
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
