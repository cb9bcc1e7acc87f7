"""Simulated straight and L-shaped walks: every filter beats PDR alone (seeded)."""

import numpy as np
import pytest

from server.estimation.tracking import make_tracker, tracker_names
from tests.helpers.simulate import run_tracker, simulate_walk

WALKS = {
    "straight": {"legs": ((30.0, 60),)},
    "L": {"legs": ((0.0, 30), (90.0, 30))},
}


@pytest.mark.parametrize("walk_name", sorted(WALKS))
@pytest.mark.parametrize("name", tracker_names())
def test_filter_beats_pdr_alone(name, walk_name):
    errors, pdr_errors = [], []
    for seed in range(3):
        walk = simulate_walk(seed=seed, **WALKS[walk_name])
        t = make_tracker(name, walk.truth[0], np.eye(2) * 0.5, seed=seed)
        est = run_tracker(t, walk)
        errors.append(np.mean(np.hypot(*(est - walk.truth).T)))
        pdr_errors.append(np.mean(np.hypot(*(walk.pdr_only() - walk.truth).T)))
    assert np.mean(errors) < 0.8 * np.mean(pdr_errors), (name, errors, pdr_errors)
