"""The Oxford step counter data set: read its traces, count steps, score the counter.

Layout: ``<root>/stats.csv`` (``#dir, user, phone, position, surface, duration(s),
steps``) and ``<root>/data/<trace>/accelerometer.csv`` with rows
``time_ns, accuracy, x, y, z`` (m/s²). ``stepcounter.csv`` holds the reference foot
sensors (``time_ns, foot1, foot2``): a 0→1 transition of either foot is one step,
which is how ``stats.csv`` was computed.
"""

from __future__ import annotations

import csv
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .pdr.step_detection import PeakDetectorParams, detect_steps_peaks


def read_accelerometer_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and (N, 3) accelerations of an accelerometer CSV (time ns, [accuracy,] x, y, z)."""
    d = np.loadtxt(path, delimiter=",", ndmin=2)
    xyz = d[:, -3:]
    return d[:, 0] * 1e-9, xyz


def count_steps(path: str | Path, params: PeakDetectorParams | None = None) -> int:
    t, acc = read_accelerometer_csv(path)
    return len(detect_steps_peaks(t, acc, params))


def count_reference_steps(stepcounter_csv: str | Path, t_from_ns: int | None = None, t_to_ns: int | None = None) -> int:
    """True steps from the foot sensors: 0→1 transitions of either foot (optionally in a window)."""
    d = np.loadtxt(stepcounter_csv, delimiter=",", ndmin=2, dtype=np.int64)
    rises = (np.diff(d[:, 1]) == 1).astype(int) + (np.diff(d[:, 2]) == 1).astype(int)
    t = d[1:, 0]
    keep = np.ones(len(t), bool)
    if t_from_ns is not None:
        keep &= t >= t_from_ns
    if t_to_ns is not None:
        keep &= t <= t_to_ns
    return int(rises[keep].sum())


@dataclass(frozen=True)
class TraceResult:
    trace: str
    position: str
    true_steps: int
    detected: int

    @property
    def error_pct(self) -> float:
        return 100.0 * abs(self.detected - self.true_steps) / self.true_steps


def read_stats(root: Path) -> list[tuple[str, str, int]]:
    """(trace, position lower-case, true steps) of every row of stats.csv."""
    rows = []
    with open(root / "stats.csv") as f:
        for row in csv.reader(f):
            if not row or row[0].startswith("#"):
                continue
            rows.append((row[0].strip(), row[3].strip().lower(), int(row[6])))
    return rows


def evaluate(root: str | Path, params: PeakDetectorParams | None = None, progress=None) -> list[TraceResult]:
    """Count steps in every trace listed in ``root/stats.csv`` that has an accelerometer file."""
    root = Path(root)
    rows = [r for r in read_stats(root) if (root / "data" / r[0] / "accelerometer.csv").exists()]
    out = []
    for trace, position, truth in (progress(rows) if progress else rows):
        out.append(TraceResult(trace, position, truth, count_steps(root / "data" / trace / "accelerometer.csv", params)))
    return out


def summarise(results: list[TraceResult]) -> dict[str, dict[str, float]]:
    """Per phone position: traces, mean and max absolute count error (%)."""
    by = defaultdict(list)
    for r in results:
        by[r.position].append(r.error_pct)
    table = {p: {"traces": len(v), "mean_error_pct": float(np.mean(v)), "max_error_pct": float(np.max(v))}
             for p, v in sorted(by.items())}
    allv = [r.error_pct for r in results]
    table["all"] = {"traces": len(allv), "mean_error_pct": float(np.mean(allv)), "max_error_pct": float(np.max(allv))}
    return table
