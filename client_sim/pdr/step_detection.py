"""Step detection on raw accelerometer samples.

Two detectors (DESIGN.md "Phone side"):

* :func:`detect_steps_peaks` — peaks of the low-pass filtered acceleration norm that
  rise above a magnitude threshold and are at least a minimum interval apart. This is
  orientation-free, so it works wherever the phone is carried.
* :func:`detect_steps_two_threshold` — on vertical (gravity-aligned) acceleration, a
  step is ``a > +1.0 m/s²`` followed by ``a < −0.8 m/s²`` within 0.6 s.

Both return the sample indices of the detected steps (for the peak detector the
index of the peak), so callers can read times and per-step acceleration extremes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal


def resample_uniform(t: np.ndarray, values: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Linearly resample irregular sensor samples onto a uniform time grid.

    Phone sensors deliver jittery timestamps; filters assume a fixed rate.
    """
    t = np.asarray(t, dtype=float)
    order = np.argsort(t, kind="stable")
    t, values = t[order], np.asarray(values, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, values = t[keep], values[keep]
    grid = np.arange(t[0], t[-1], 1.0 / rate_hz)
    if values.ndim == 1:
        return grid, np.interp(grid, t, values)
    return grid, np.column_stack([np.interp(grid, t, values[:, i]) for i in range(values.shape[1])])


def lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass (offline: a batch of samples is at hand)."""
    sos = signal.butter(order, cutoff_hz, btype="low", fs=rate_hz, output="sos")
    if len(x) <= 3 * (2 * order + 1):
        return np.asarray(x, dtype=float) - 0.0
    return signal.sosfiltfilt(sos, x)


@dataclass(frozen=True)
class PeakDetectorParams:
    """Thresholds of the peak detector; defaults tuned on the Oxford step counter set."""

    rate_hz: float = 100.0
    cutoff_hz: float = 3.0  # walking cadence is 1.4–2.4 Hz; 3 Hz keeps one bump per step
    min_peak: float = 0.5  # m/s² above the running mean of the norm
    min_interval_s: float = 0.35  # no two steps closer than this (walking, ≤ 2.9 steps/s)
    min_prominence: float = 1.0  # m/s²; rejects ripples riding on one step
    detrend_window_s: float = 2.0  # running-mean window that removes gravity


def acceleration_signal(t: np.ndarray, acc: np.ndarray, p: PeakDetectorParams) -> tuple[np.ndarray, np.ndarray]:
    """Uniform-rate, detrended, smoothed acceleration norm (m/s²) and its time grid."""
    norm = np.linalg.norm(np.asarray(acc, dtype=float), axis=1)
    grid, norm = resample_uniform(t, norm, p.rate_hz)
    win = max(1, int(round(p.detrend_window_s * p.rate_hz)))
    # running mean with edge correction (zero padding would fake peaks at both ends)
    ones = np.ones(win)
    trend = np.convolve(norm, ones, mode="same") / np.convolve(np.ones_like(norm), ones, mode="same")
    return grid, lowpass(norm - trend, p.rate_hz, p.cutoff_hz)


@dataclass(frozen=True)
class StepPeaks:
    """Detected steps: time of each peak and the acceleration extremes around it (m/s²)."""

    t: np.ndarray
    a_max: np.ndarray
    a_min: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


def find_step_peaks(t: np.ndarray, acc: np.ndarray, params: PeakDetectorParams | None = None) -> StepPeaks:
    """Steps as peaks of the smoothed, detrended acceleration norm.

    ``a_min`` of a step is the lowest value between the previous peak (or 0.6 s
    before the first) and this one: the Weinberg step length wants that swing.
    """
    p = params or PeakDetectorParams()
    grid, smooth = acceleration_signal(t, acc, p)
    peaks, _ = signal.find_peaks(
        smooth,
        height=p.min_peak,
        distance=max(1, int(p.min_interval_s * p.rate_hz)),
        prominence=p.min_prominence,
    )
    starts = np.concatenate([[max(0, peaks[0] - int(0.6 * p.rate_hz))], peaks[:-1]]) if len(peaks) else peaks
    a_min = np.array([smooth[s:e + 1].min() for s, e in zip(starts, peaks, strict=True)])
    return StepPeaks(grid[peaks], smooth[peaks], a_min)


def detect_steps_peaks(t: np.ndarray, acc: np.ndarray, params: PeakDetectorParams | None = None) -> np.ndarray:
    """Times (s, same clock as ``t``) of steps found as peaks of the smoothed norm."""
    return find_step_peaks(t, acc, params).t


def detect_steps_two_threshold(
    t: np.ndarray, a_vertical: np.ndarray, upper: float = 1.0, lower: float = -0.8, window_s: float = 0.6
) -> np.ndarray:
    """Times of steps by the two-threshold rule on gravity-free vertical acceleration.

    A step starts when ``a`` exceeds ``upper`` and is confirmed when ``a`` falls below
    ``lower`` within ``window_s``; the step time is the moment of the upper crossing.
    """
    t = np.asarray(t, dtype=float)
    a = np.asarray(a_vertical, dtype=float)
    steps: list[float] = []
    armed_at: float | None = None
    for ti, ai in zip(t, a, strict=True):
        if armed_at is not None and ti - armed_at > window_s:
            armed_at = None
        if armed_at is None:
            if ai > upper:
                armed_at = ti
        elif ai < lower:
            steps.append(armed_at)
            armed_at = None
    return np.array(steps)
