"""A tiny seeded walk simulator for tests and benchmarks (no radio model).

An L-shaped (or straight) walk of fixed-length steps; the PDR reports each step with
a length error and a heading bias plus noise; every ``fix_every`` steps a fix is drawn
around the true position with an isotropic error of ``fix_std_m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.estimation.types import Fix, Step, step_displacement


@dataclass
class SimulatedWalk:
    truth: np.ndarray  # (n_steps + 1, 2): start, then after each step
    events: list  # Steps and Fixes in time order
    step_index: list[int]  # for each event, the number of steps applied so far

    def pdr_only(self) -> np.ndarray:
        pos = [self.truth[0].copy()]
        for e in self.events:
            if isinstance(e, Step):
                pos.append(pos[-1] + step_displacement(e.length_m, e.heading_deg))
        return np.array(pos)


def simulate_walk(
    seed: int = 0,
    legs: tuple[tuple[float, int], ...] = ((0.0, 30), (90.0, 30)),
    step_m: float = 0.7,
    length_noise_m: float = 0.07,
    heading_bias_deg: float = 6.0,
    heading_noise_deg: float = 4.0,
    fix_every: int = 3,
    fix_std_m: float = 1.5,
    start=(0.0, 0.0),
) -> SimulatedWalk:
    rng = np.random.default_rng(seed)
    truth = [np.asarray(start, float)]
    events: list = []
    idx: list[int] = []
    k = 0
    for heading, n in legs:
        for _ in range(n):
            truth.append(truth[-1] + step_displacement(step_m, heading))
            k += 1
            events.append(
                Step(
                    float(k),
                    step_m + length_noise_m * rng.standard_normal(),
                    heading + heading_bias_deg + heading_noise_deg * rng.standard_normal(),
                    length_std_m=max(length_noise_m, 0.05),
                    heading_std_deg=heading_noise_deg + abs(heading_bias_deg),
                )
            )
            idx.append(k)
            if k % fix_every == 0:
                z = truth[-1] + fix_std_m * rng.standard_normal(2)
                events.append(Fix(float(z[0]), float(z[1]), 0, np.eye(2) * fix_std_m**2))
                idx.append(k)
    return SimulatedWalk(np.array(truth), events, idx)


def run_tracker(tracker, walk: SimulatedWalk) -> np.ndarray:
    """Estimates after each step (fixes applied as they come); row 0 is the start."""
    out = [tracker.mean]
    for e in walk.events:
        if isinstance(e, Step):
            tracker.predict(e)
            out.append(tracker.mean)
        else:
            tracker.update(e)
            out[-1] = tracker.mean
    return np.array(out)
