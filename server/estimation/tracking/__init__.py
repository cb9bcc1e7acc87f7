"""Trackers fusing PDR steps with position fixes, and their helpers.

Public entry points::

    make_tracker(name, initial_mean, initial_cov, walls=None, seed=None, **params) -> Tracker
    tracker_from_dict(d) -> Tracker          # d = tracker.to_dict()
    tracker_names() -> ["ekf", "fkf", "kf", "pf", "skpf", "ukf"]

Each Tracker has predict(step), update(fix), update_range(beacon_xy, range_m,
range_std_m, on_wall=None) -> bool, mean, covariance, reset(mean, cov),
set_walls(walls), search_region(), to_dict(), from_dict().
"""

from server.estimation.tracking.base import TRACKERS, Tracker, make_tracker, tracker_from_dict, tracker_names
from server.estimation.tracking.crowd import find_merge_target, gate, make_crowd_point, merge_points
from server.estimation.tracking.ekf import EKFTracker
from server.estimation.tracking.fkf import FuzzyKFTracker
from server.estimation.tracking.floors import FloorTracker
from server.estimation.tracking.kf import KFTracker
from server.estimation.tracking.landmarks import LandmarkCorrector, Snap, apply_snap
from server.estimation.tracking.pf import ParticleFilterTracker
from server.estimation.tracking.skpf import SKPFTracker
from server.estimation.tracking.ukf import UKFTracker

__all__ = [
    "TRACKERS",
    "Tracker",
    "make_tracker",
    "tracker_from_dict",
    "tracker_names",
    "KFTracker",
    "EKFTracker",
    "UKFTracker",
    "ParticleFilterTracker",
    "SKPFTracker",
    "FuzzyKFTracker",
    "FloorTracker",
    "LandmarkCorrector",
    "Snap",
    "apply_snap",
    "gate",
    "make_crowd_point",
    "find_merge_target",
    "merge_points",
]
