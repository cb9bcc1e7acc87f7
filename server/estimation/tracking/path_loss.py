"""Range from RSS with the log-distance path-loss model RSS = R0 − 10·γ·log10(d).

Inverting: d = 10^((R0 − RSS) / (10·γ)). An RSS error of σ dBm maps, to first order,
to a range error σ_d = d · ln(10) · σ / (10·γ) (the range error grows with range,
which is why beacon ranges are only used close to the beacon).
"""

from __future__ import annotations

import math


def range_from_rss(rss_dbm: float, r0_dbm: float, gamma: float) -> float:
    """Distance in metres at which the model predicts ``rss_dbm`` (R0 is the RSS at 1 m)."""
    if gamma <= 0:
        raise ValueError("path-loss exponent gamma must be positive")
    return 10.0 ** ((r0_dbm - rss_dbm) / (10.0 * gamma))


def range_std_from_rss(range_m: float, rss_std_db: float, gamma: float) -> float:
    """First-order standard deviation of the range for an RSS noise of ``rss_std_db``."""
    if gamma <= 0:
        raise ValueError("path-loss exponent gamma must be positive")
    return range_m * math.log(10.0) * rss_std_db / (10.0 * gamma)


def range_and_std(rss_dbm: float, r0_dbm: float, gamma: float, rss_std_db: float = 4.0) -> tuple[float, float]:
    """(range_m, range_std_m) for one RSS reading."""
    d = range_from_rss(rss_dbm, r0_dbm, gamma)
    return d, range_std_from_rss(d, rss_std_db, gamma)
