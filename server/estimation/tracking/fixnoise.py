"""How much a session's fingerprint fixes really scatter, learned from their innovations.

A model's fix covariance R is calibrated on its own survey (held-out reference points),
but a live phone's scans are noisier than the survey's averaged ones (a body in the way,
another device, a moving crowd) and a site's radio map may be worse than its held-out
points suggest. A tracker that takes R as given is then overconfident: it refuses good
fixes or is pulled around by bad ones. So each session estimates a scale ``s`` with
E[y yᵀ] = P + s·R (covariance matching, Mehra 1972) from the innovations y of its fixes,
P being the tracker's covariance before the update:

    s_i = (yᵀ R⁻¹ y − tr(R⁻¹ P)) / 2         (an unbiased sample of s for a 2-D fix)

averaged with exponential forgetting (a window of about ``WINDOW`` fixes) and a prior of
``PRIOR_WEIGHT`` fixes at s = 1. Each sample is clipped to [0, ``SAMPLE_MAX_RATIO`` · s],
so one fix from the wrong end of the building moves the scale by a bounded fraction
while a run of them can still grow it; refused fixes count too (otherwise an
overconfident R could never learn that it is). The scale is
kept within [``SCALE_MIN``, ``SCALE_MAX``]. Fixes are then used (gate and update) with
covariance s·R.

A fingerprint model's errors are not independent from fix to fix: a walker crossing a
badly surveyed stretch gets several fixes pulled the same way, and a filter that takes them
as independent grows confident in the bias (its NEES then exceeds the fixes' NIS). So the
session also learns the lag-1 correlation ρ of successive whitened innovations
(u = L⁻¹y, S = L Lᵀ = P + s·R; samples uᵢ·uᵢ₋₁/2 with the same forgetting and a prior of
``PRIOR_WEIGHT`` fixes at 0), and uses fixes with covariance s·R·(1 + ρ)/(1 − ρ), the
information n AR(1)-correlated fixes carry against n independent ones.

Fixes also have heavy tails (a scan that resembles another corridor), so an accepted fix
updates with a Student-t likelihood (one variational step: its covariance times
(ν + d²)/(ν + 2), d² its squared Mahalanobis distance): near fixes keep their weight, far
ones lose it smoothly instead of all or nothing at the gate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: fixes of memory (forgetting factor 1 − 1/WINDOW)
WINDOW = 30.0
#: the prior's weight in fixes, at s = 1 (the model's own calibration)
PRIOR_WEIGHT = 4.0
#: largest single sample, as a multiple of the current scale (chosen on the tune scenarios
#: among 5, 10, 20; a gross outlier moves the
#: scale by at most that many times itself over the weight)
SAMPLE_MAX_RATIO = 10.0
SCALE_MIN = 0.5
SCALE_MAX = 25.0
#: degrees of freedom of the Student-t fix likelihood (chosen on the tune scenarios of
#: benchmarks/scenario_family.py among 3, 4, 6, 10; 3–6 were within 3 % of each other)
STUDENT_NU = 4.0
#: the largest lag-1 correlation of successive fixes' errors believed (a factor of 3 on R;
#: chosen on the tune scenarios among 0 (off), 0.5 and 0.8, which differed by < 1 %)
RHO_MAX = 0.5


def student_t_factor(d2: float) -> float:
    """Covariance factor for a fix at squared Mahalanobis distance ``d2`` under a Student-t
    likelihood with ``STUDENT_NU`` degrees of freedom (one variational step): fixes near
    the estimate keep their weight, far ones lose it smoothly instead of at the gate."""
    return max(1.0, (STUDENT_NU + d2) / (STUDENT_NU + 2.0))


@dataclass
class FixNoiseScale:
    """Running weighted mean of the scale samples; ``total`` and ``weight`` exclude the prior."""

    total: float = 0.0
    weight: float = 0.0
    #: running sum of lag-1 correlation samples of the whitened innovations (same forgetting)
    corr_total: float = 0.0
    #: the previous fix's whitened innovation (None before the first)
    prev: tuple[float, float] | None = None

    @property
    def scale(self) -> float:
        s = (PRIOR_WEIGHT + self.total) / (PRIOR_WEIGHT + self.weight)
        return float(min(max(s, SCALE_MIN), SCALE_MAX))

    @property
    def correlation(self) -> float:
        """Lag-1 correlation of successive fixes' whitened innovations, kept in [0, RHO_MAX]."""
        rho = self.corr_total / (PRIOR_WEIGHT + self.weight)
        return float(min(max(rho, 0.0), RHO_MAX))

    @property
    def factor(self) -> float:
        """What correlated fix errors cost: n fixes whose errors follow an AR(1) with lag-1
        correlation ρ carry the information of n·(1 − ρ)/(1 + ρ) independent ones."""
        rho = self.correlation
        return (1.0 + rho) / (1.0 - rho)

    @property
    def multiplier(self) -> float:
        """What a fix's own covariance is multiplied by: scale × correlation factor."""
        return self.scale * self.factor

    def observe(self, innovation: np.ndarray, P: np.ndarray, R: np.ndarray) -> None:
        """Learn from one fix: ``innovation`` = fix − estimate, ``P`` the tracker's position
        covariance before the update, ``R`` the fix's own (unscaled) covariance."""
        y = np.asarray(innovation, float)
        Rinv = np.linalg.inv(np.asarray(R, float))
        sample = (float(y @ Rinv @ y) - float(np.trace(Rinv @ np.asarray(P, float)))) / 2.0
        L = np.linalg.cholesky(np.asarray(P, float) + self.multiplier * np.asarray(R, float))
        u = np.linalg.solve(L, y)
        u = u / max(1.0, float(np.hypot(*u)) / 3.0)  # an outlier's direction, not its size
        corr = 0.0 if self.prev is None else float(u @ np.asarray(self.prev)) / 2.0
        sample = min(max(sample, 0.0), SAMPLE_MAX_RATIO * self.scale)
        keep = 1.0 - 1.0 / WINDOW
        self.total = keep * self.total + sample
        self.corr_total = keep * self.corr_total + corr
        self.weight = keep * self.weight + 1.0
        self.prev = (float(u[0]), float(u[1]))

    def to_list(self) -> list[float]:
        prev = [] if self.prev is None else list(self.prev)
        return [self.total, self.weight, self.corr_total, *prev]

    @classmethod
    def from_list(cls, data: list[float] | None) -> FixNoiseScale:
        """A stored list; None (a state stored before this existed) starts at the prior, and
        a pair (stored before the correlation was learned) starts it at 0."""
        if data is None:
            return cls()
        v = [float(x) for x in data]
        prev = (v[3], v[4]) if len(v) >= 5 else None
        return cls(v[0], v[1], v[2] if len(v) >= 3 else 0.0, prev)
