"""Every tracker parameter a session may set (``tracking.tuning``) keeps the tracker working at
both ends of its range: a step, a fix and a beacon range give a finite estimate."""

from __future__ import annotations

import numpy as np
import pytest

from server.estimation.tracking import make_tracker, tracker_names
from server.estimation.tracking.tuning import TUNABLE, BadParam, check_params, tunable_params
from server.estimation.types import Fix, Step

#: walls along x and y far from the walk: a grid at 0° that kills no particle
FAR_GRID = [[500.0, -50.0, 500.0, 50.0], [450.0, 0.0, 550.0, 0.0]]
CASES = [(f, name, end) for f in tracker_names() for name in tunable_params(f) for end in ("lo", "hi")
         if not (name == "min_particles" and end == "hi")]  # (above the default count: refused together, below)


@pytest.mark.parametrize("filter, name, end", CASES)
def test_each_end_of_each_range_gives_a_working_tracker(filter, name, end):
    spec = TUNABLE[name]
    params = check_params(filter, {name: getattr(spec, end)})
    t = make_tracker(filter, [0.0, 0.0], np.eye(2), seed=1, walls=FAR_GRID, **params)
    for k in range(8):  # straight along the walls' grid: the grid heading reference fires at least once
        t.predict(Step(float(k), 0.7, 10.0))
        t.update(Fix(0.5, 1.5 + 0.7 * k, 0, np.eye(2) * 4.0))
        t.update_range([2.0, 2.0 + 0.7 * k], 2.5, 1.0)
    assert np.all(np.isfinite(t.mean)) and np.all(np.isfinite(t.covariance)), (filter, name, end)


def test_min_particles_above_the_count_is_refused_naming_the_parameters():
    with pytest.raises(BadParam, match="min_particles") as caught:
        check_params("pf", {"min_particles": 5000})
    assert caught.value.name is None  # the two together, not one value
    assert check_params("pf", {"n_particles": 5000, "min_particles": 5000}) == {"n_particles": 5000,
                                                                                "min_particles": 5000}


def test_a_particle_count_alone_is_a_fixed_count():
    t = make_tracker("pf", [0, 0], np.eye(2), seed=1, **check_params("pf", {"n_particles": 300}))
    assert t.params["min_particles"] == 300 and len(t.particles) == 300
