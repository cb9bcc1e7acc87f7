"""The tracker parameters a session may set, and their checks.

A session's ``filter_params`` (an API extension) override a tracker's defaults: an operator
tunes a site's trackers, an evaluation compares settings on the same walks and seeds. Only
numeric parameters listed in ``TUNABLE`` may be set, each within a range that keeps the
tracker well defined and a session's cost bounded (a PF's particle count is its CPU per
step and its stored state per batch); which of them a filter takes is what its default
instance records in ``Tracker.params``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from server.estimation.tracking.base import make_tracker, tracker_names


@dataclass(frozen=True)
class Tunable:
    """A parameter's inclusive range and what it measures; ``integer``: it counts something."""

    lo: float
    hi: float
    unit: str
    integer: bool = False


#: every parameter a session may set, by name (the same name means the same thing in every filter)
TUNABLE: dict[str, Tunable] = {
    "q": Tunable(0.0, 100.0, "m² of position jitter per step"),
    "r": Tunable(1e-4, 1e4, "m² fix variance (kf)"),
    "n_particles": Tunable(2, 10_000, "particles", integer=True),
    "min_particles": Tunable(2, 10_000, "KLD-sampling's fewest particles", integer=True),
    "kld_bin_m": Tunable(0.01, 100.0, "KLD-sampling's bin, m"),
    "kld_epsilon": Tunable(0.001, 1.0, "KLD-sampling's error bound"),
    "resample_threshold": Tunable(0.0, 1.0, "resample below this share of effective particles"),
    "resample_kills": Tunable(0, 1, "1: resample whenever a wall kills, 0: only below resample_threshold",
                              integer=True),
    "min_survivors": Tunable(0.0, 10_000.0, "effective survivors of a wall kill below which the cloud is "
                             "spread by a kernel (pf; 0: off)"),
    "max_range_m": Tunable(0.0, 100.0, "m, longest beacon range used"),
    "wall_margin_m": Tunable(0.0, 5.0, "m kept from a wall"),
    "alpha": Tunable(1e-3, 10.0, "sigma-point spread"),
    "beta": Tunable(0.0, 10.0, "sigma-point prior weight"),
    "kappa": Tunable(0.0, 10.0, "sigma-point secondary scaling"),
    "bias0_std_deg": Tunable(0.0, 180.0, "° heading-bias prior"),
    "bias_walk_deg": Tunable(0.0, 45.0, "° heading-bias random walk per step"),
    "fix_bias_share": Tunable(0.0, 0.95, "share of a fix's variance shared along the walk (pf, with a plan)"),
    "fix_bias_steps": Tunable(1.0, 10_000.0, "steps, correlation length of the fixes' shared error (pf)"),
    "fix_bias_switch": Tunable(0.0, 0.5, "probability per step that a particle's hypothesis of the fixes' shared "
                               "error flips (pf; 0: the share is not learned)"),
    "walk_offset": Tunable(0, 2, "1: estimate the walk's fix offset from fixes that carry the map's walk share, "
                           "2: account for it without estimating it (ekf)", integer=True),
    "kalman_floor": Tunable(0.0, 1.0, "share of its shortfall from a Kalman update the cloud makes up "
                            "after a fix, beacon range or grid run (pf, no plan)"),
    "grid_sigma_deg": Tunable(0.0, 45.0, "° σ of the building's grid as a heading reference, per straight run "
                              "(0: off; ekf, ukf, skpf, pf; the walls' grid, else the survey's)"),
    "grid_gate_deg": Tunable(0.0, 45.0, "° largest offset of a straight run from the grid that is observed"),
    "grid_steps": Tunable(1, 1000, "a straight run observes the grid every this many steps", integer=True),
    "grid_plan": Tunable(0, 1, "0: the pf leaves the grid out on a floor with a plan (default 1: the walls' grid)", integer=True),
    "grid_on_share": Tunable(0.01, 1.0, "share of straight runs taken as on the grid, the rest at any angle (pf)"),
    "search_sigmas": Tunable(0.0, 100.0, "the fingerprint model looks within this many of the tracker's largest "
                             "position σ (+ search_margin_m) of its estimate (0: anywhere; ekf, ukf, skpf, pf without a plan; "
                             "a model trained on crowd fingerprints always answers anywhere)"),
    "search_margin_m": Tunable(0.0, 10_000.0, "m added to the fingerprint model's search radius"),
    "scale0_std": Tunable(0.0, 1.0, "step-scale prior"),
    "scale_walk": Tunable(0.0, 0.5, "step-scale random walk per step"),
    "box_half_width_m": Tunable(0.1, 1000.0, "m (fkf)"),
    "reset_every": Tunable(1, 10_000, "steps (fkf)", integer=True),
    "lost_after": Tunable(1, 1000, "fixes (fkf)", integer=True),
}


class BadParam(ValueError):
    """A parameter that cannot be set; ``name`` None: the parameters together (a tracker's cross-check)."""

    def __init__(self, name: str | None, msg: str):
        super().__init__(msg)
        self.name = name


@cache
def tunable_params(filter: str) -> dict[str, Any]:
    """The parameters ``filter`` takes that a session may set, with their defaults."""
    defaults = make_tracker(filter, [0.0, 0.0], np.eye(2), seed=0).params
    return {k: v for k, v in defaults.items() if k in TUNABLE}


def check_params(filter: str, params: dict[str, Any]) -> dict[str, float | int]:
    """``params`` for ``filter`` as its constructor takes them; ``BadParam`` naming the first
    parameter that is unknown, not a finite number, not whole where it counts, out of range,
    or inconsistent with the others (the tracker's own check, e.g. min_particles > n_particles)."""
    if not params:
        return {}
    known = tunable_params(filter)
    out: dict[str, float | int] = {}
    for name, value in params.items():
        if name not in known:
            raise BadParam(name, f"{name!r} is not a parameter of {filter} (one of {', '.join(sorted(known))})")
        spec = TUNABLE[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                isinstance(value, float) and not math.isfinite(value)):
            raise BadParam(name, f"{name} must be a finite number, not {str(value)[:40]}")
        if not spec.lo <= value <= spec.hi:  # (an int of any size compares exactly)
            raise BadParam(name, f"{name} must be between {spec.lo:g} and {spec.hi:g}, not {str(value)[:40]}")
        if spec.integer and isinstance(value, float) and not value.is_integer():
            raise BadParam(name, f"{name} must be a whole number, not {value!r}")
        out[name] = int(value) if spec.integer else float(value)
    try:
        make_tracker(filter, [0.0, 0.0], np.eye(2), seed=0, **out)  # the tracker's own cross-checks
    except ValueError as exc:
        raise BadParam(None, str(exc)) from None
    return out


def params_doc() -> str:
    """The parameters each filter takes (for the API schema's description)."""
    def one(name: str, default: float) -> str:
        spec = TUNABLE[name]
        unit = f"{spec.unit}, " if spec.unit else ""
        return f"{name} ({unit}{spec.lo:g}–{spec.hi:g}, default {default:g})"

    return "; ".join(f"`{f}`: " + ", ".join(one(k, v) for k, v in tunable_params(f).items()) for f in tracker_names())
