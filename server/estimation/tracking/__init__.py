"""Trackers fusing PDR steps with position fixes, and their helpers.

Public entry points::

    make_tracker(name, initial_mean, initial_cov, walls=None, seed=None, **params) -> Tracker
    tracker_from_dict(d) -> Tracker          # d = tracker.to_dict()
    tracker_names() -> ["ekf", "ekf-xy", "fkf", "kf", "pf", "pf-xy", "skpf", "skpf-xy", "ukf", "ukf-xy"]

``ekf``, ``ukf``, ``pf`` and ``skpf`` are self-calibrating (state [x, y, heading bias, step
scale], ``selfcal``); ``<name>-xy`` is each one's two-state seed form; ``kf`` and ``fkf``
are linear two-state filters.

    smooth_track(estimates) -> estimates       # RTS smoother over a stored track

Each Tracker has predict(step), update(fix), update_range(beacon_xy, range_m,
range_std_m, on_wall=None) -> bool, mean, covariance, reset(mean, cov),
set_walls(walls), inflate(factor), search_region(), to_dict(), from_dict().
"""

from server.estimation.tracking.base import TRACKERS, Tracker, make_tracker, tracker_from_dict, tracker_names
from server.estimation.tracking.crowd import find_merge_target, gate, make_crowd_point, merge_points
from server.estimation.tracking.ekf import EKFTracker, EKFXYTracker
from server.estimation.tracking.fkf import FuzzyKFTracker
from server.estimation.tracking.floors import FloorTracker
from server.estimation.tracking.kf import KFTracker
from server.estimation.tracking.landmarks import LandmarkCorrector, Snap, apply_snap
from server.estimation.tracking.pf import ParticleFilterTracker, ParticleFilterXYTracker
from server.estimation.tracking.skpf import SKPFTracker, SKPFXYTracker
from server.estimation.tracking.smoother import smooth_track
from server.estimation.tracking.ukf import UKFTracker, UKFXYTracker

__all__ = [
    "TRACKERS",
    "Tracker",
    "make_tracker",
    "tracker_from_dict",
    "tracker_names",
    "KFTracker",
    "EKFTracker",
    "EKFXYTracker",
    "UKFTracker",
    "UKFXYTracker",
    "ParticleFilterTracker",
    "ParticleFilterXYTracker",
    "SKPFTracker",
    "SKPFXYTracker",
    "FuzzyKFTracker",
    "FloorTracker",
    "LandmarkCorrector",
    "Snap",
    "apply_snap",
    "gate",
    "make_crowd_point",
    "find_merge_target",
    "merge_points",
    "smooth_track",
]
