"""Where a self-calibrating tracker lets the fingerprint model look (``Calibrating.search_region``):
within ``search_sigmas`` × its largest position σ + ``search_margin_m`` of its estimate, so that a
scan resembling a far part of the building gives the best match near the walker."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from server.estimation.session import SessionEstimator
from server.estimation.tracking import make_tracker
from server.estimation.tracking.selfcal import SEARCH_MARGIN_M, SEARCH_SIGMAS
from server.estimation.types import Area, Fix, Scan, SiteMap, Step
from tests.estimation.test_session_walk import ModelFixes, rss_at

CALIBRATING = ["ekf", "ukf", "skpf", "pf"]
#: a corridor's two walls far from the start (a plan for the PF)
WALLS = [[-50.0, -1.5, 50.0, -1.5], [-50.0, 1.5, 50.0, 1.5]]


def _started(name: str, **params) -> SessionEstimator:
    est = SessionEstimator(name, seed=1, tracker_params=params)
    est.start([10.0, 5.0], np.diag([4.0, 1.0]), 0, [], None, "init")  # largest σ 2 m along x
    return est


@pytest.mark.parametrize("name", CALIBRATING)
def test_the_model_looks_within_three_sigma_and_ten_metres_of_the_estimate(name):
    est = _started(name)
    area = est.search_area()
    assert area is not None
    sd = math.sqrt(np.linalg.eigvalsh(est.tracker.covariance)[-1])
    assert sd == pytest.approx(2.0, rel=0.1)  # (the PF's cloud is drawn)
    assert (area.x, area.y) == pytest.approx(tuple(est.tracker.mean))
    assert area.radius_m == pytest.approx(SEARCH_SIGMAS * sd + SEARCH_MARGIN_M)


@pytest.mark.parametrize("name", CALIBRATING)
def test_the_gates_widening_widens_the_search_with_it(name):
    est = _started(name)
    before = est.search_area()
    est.tracker.inflate(4.0)
    after = est.search_area()
    assert before is not None and after is not None
    assert after.radius_m - SEARCH_MARGIN_M == pytest.approx(2.0 * (before.radius_m - SEARCH_MARGIN_M), rel=1e-6)


@pytest.mark.parametrize("name", CALIBRATING)
def test_search_sigmas_zero_lets_the_model_look_anywhere(name):
    assert _started(name, search_sigmas=0.0).search_area() is None
    area = _started(name, search_sigmas=0.5, search_margin_m=0.0).search_area()
    assert area is not None and area.radius_m == pytest.approx(1.0, rel=0.1)  # even inside one σ


@pytest.mark.parametrize("name", ["kf", "ekf-xy", "ukf-xy", "pf-xy", "skpf-xy"])
def test_the_seed_forms_look_anywhere(name):
    assert _started(name).search_area() is None


def test_a_pf_with_a_plan_looks_anywhere():
    """Walls narrow its cloud, and a narrow cloud fed the matches near itself confirms itself."""
    free = make_tracker("pf", [0.0, 0.0], np.eye(2), seed=1)
    walled = make_tracker("pf", [0.0, 0.0], np.eye(2), seed=1, walls=WALLS)
    assert free.search_region() is not None
    assert walled.search_region() is None


class Recording:
    """The model's fixes, each kept with the area it was asked for."""

    def __init__(self, fixes: ModelFixes):
        self.inner, self.asked = fixes, []

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        f = self.inner.fix(scan, near)
        self.asked.append((near, f))
        return f


@pytest.fixture(scope="module")
def model() -> ModelFixes:
    return ModelFixes()


def _far_scan(name: str, model: ModelFixes, **params) -> tuple[Area | None, Fix]:
    """A walker at the loop's corner (0, 0) whose scan sounds like the opposite corner (40, 20):
    the area the model was asked for and its fix."""
    est = SessionEstimator(name, seed=1, tracker_params=params)
    est.start([0.0, 0.0], np.eye(2), 0, [], None, "init")
    rec = Recording(model)
    est.apply_batch([Step(1.0, 0.7, 90.0)], [Scan(1.5, rss_at(40.0, 20.0))], rec, SiteMap())
    (near, fix), = rec.asked
    return near, fix


@pytest.mark.parametrize("name", CALIBRATING)
def test_a_scan_like_a_far_corner_gives_the_best_match_near_the_walker(name, model):
    near, fix = _far_scan(name, model)
    assert near is not None
    assert math.hypot(fix.x - near.x, fix.y - near.y) <= near.radius_m < 20.0
    # the same scan searched anywhere: the far corner, 44 m from the walker
    near, far = _far_scan(name, model, search_sigmas=0.0)
    assert near is None and math.hypot(far.x - 40.0, far.y - 20.0) < 6.0
    assert math.hypot(fix.x - 0.7, fix.y) < math.hypot(far.x - 0.7, far.y) - 20.0


def test_a_model_trained_on_crowd_fingerprints_answers_anywhere(model):
    """Its positions are earlier sessions' beliefs: the circle would let them confirm a session's error."""
    crowd = copy.copy(model)
    crowd.model = copy.copy(model.model)  # (the module's model stays survey-only)
    crowd.model.crowd_share_ = 0.5
    near, fix = _far_scan("ekf", crowd)
    assert near is not None  # the session still asks for its circle ...
    assert math.hypot(fix.x - 40.0, fix.y - 20.0) < 6.0  # ... and the model answers with the far corner
    assert math.hypot(fix.x - near.x, fix.y - near.y) > near.radius_m


@pytest.mark.parametrize("name", CALIBRATING)
def test_a_session_stored_before_the_search_rule_searches_from_its_next_scan(name):
    """Its stored parameters lack the two names: they load with the defaults."""
    state = _started(name).to_dict()
    for key in ("search_sigmas", "search_margin_m"):
        del state["tracker"]["params"][key]
    restored = SessionEstimator.from_dict(state)
    area = restored.search_area()
    assert area is not None and area.radius_m > SEARCH_MARGIN_M
    assert restored.tracker.params["search_sigmas"] == SEARCH_SIGMAS
