"""to_dict/from_dict round-trips: a restored tracker gives identical future outputs."""

import json

import numpy as np
import pytest

from server.estimation.tracking import Tracker, make_tracker, tracker_from_dict, tracker_names
from server.estimation.tracking.base import TRACKERS
from server.estimation.types import Fix, Step

WALLS = [[-10.0, 3.0, 10.0, 3.0], [4.0, -10.0, 4.0, 10.0]]


def _inputs(seed):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(12):
        out.append(Step(k, 0.5 + 0.3 * rng.random(), 360 * rng.random(), 0.1, 6.0))
        if k % 3 == 2:
            out.append(Fix(*rng.normal(size=2), 0, np.diag(rng.uniform(0.5, 2.0, 2))))
    return out


def _apply(t, items):
    trace = []
    for item in items:
        if isinstance(item, Step):
            t.predict(item)
        else:
            t.update(item)
        trace.append((t.mean.tolist(), t.covariance.tolist()))
    return trace


def test_registry_has_all_trackers():
    assert tracker_names() == ["ekf", "ekf-xy", "fkf", "kf", "pf", "pf-xy", "skpf", "skpf-xy", "ukf", "ukf-xy"]
    with pytest.raises(ValueError):
        make_tracker("nope", [0, 0], np.eye(2))


@pytest.mark.parametrize("name", sorted(TRACKERS))
def test_round_trip_gives_identical_future_outputs(name):
    t = make_tracker(name, [0.5, -0.5], np.eye(2), walls=WALLS, seed=11)
    items = _inputs(1)
    _apply(t, items[:8])
    stored = json.loads(json.dumps(t.to_dict(), allow_nan=False))  # JSON-safe
    assert stored["filter"] == name
    restored = tracker_from_dict(stored)
    assert type(restored) is type(t)
    np.testing.assert_array_equal(restored.mean, t.mean)
    np.testing.assert_array_equal(restored.covariance, t.covariance)
    future = items[8:] + _inputs(2)
    assert _apply(restored, future) == _apply(t, future)
    assert restored.to_dict() == t.to_dict()


def test_pf_round_trip_restores_rng_state():
    t = make_tracker("pf", [0, 0], np.eye(2), seed=5)
    restored = Tracker.from_dict(json.loads(json.dumps(t.to_dict())))
    step = Step(0, 0.7, 45.0)
    t.predict(step)
    restored.predict(step)
    np.testing.assert_array_equal(restored.particles, t.particles)
    # and a different seed really gives a different cloud
    other = make_tracker("pf", [0, 0], np.eye(2), seed=6)
    other.predict(step)
    assert not np.array_equal(other.particles, t.particles)


@pytest.mark.parametrize("name", ["pf", "pf-xy"])
def test_pf_restores_its_own_parameters_without_default_ones(name):
    """A PF restores with the parameters it was made with (``_restore`` configures it without
    drawing a default cloud first), and continues as the original."""
    params = {"n_particles": 300, "min_particles": 300, "q": 0.05}
    if name == "pf":
        params["bias0_std_deg"] = 20.0
    t = make_tracker(name, [1.0, 2.0], np.eye(2) * 3.0, walls=WALLS, seed=9, **params)
    restored = tracker_from_dict(json.loads(json.dumps(t.to_dict())))
    assert type(restored) is type(t) and restored.params == t.params and len(restored.particles) == 300
    assert restored.walls.tolist() == t.walls.tolist()
    assert _apply(restored, _inputs(4)) == _apply(t, _inputs(4))


def test_from_dict_rejects_wrong_class_and_version():
    d = make_tracker("kf", [0, 0], np.eye(2)).to_dict()
    with pytest.raises(ValueError):
        TRACKERS["ekf"].from_dict(d)
    with pytest.raises(ValueError):
        tracker_from_dict({**d, "version": 99})


@pytest.mark.parametrize("name", ["ekf", "ukf", "pf", "skpf"])
def test_singular_fix_covariance_is_floored_not_fatal(name):
    # A fingerprint model sure of one reference point may answer with a zero covariance.
    t = make_tracker(name, [0, 0], np.eye(2), seed=0)
    t.update(Fix(1.0, 1.0, 0, np.zeros((2, 2))))
    assert np.all(np.isfinite(t.mean)) and np.linalg.det(t.covariance) > 0
    assert np.hypot(*(t.mean - 1.0)) < 0.5  # pulled hard towards the fix
    with pytest.raises(ValueError):
        t.update(Fix(1.0, 1.0, 0, np.full((2, 2), np.nan)))
