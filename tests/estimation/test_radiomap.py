"""The interpolated radio map ("rmap") on a synthetic floor surveyed every 6 m."""

import numpy as np
import pytest

from server.estimation.fingerprint import fit_and_validate, from_bytes, make_model, to_bytes
from server.estimation.fingerprint.radiomap import RadioMapModel
from tests.helpers.synthetic import make_site

SPACING = 6.0


def _floor(seed: int):
    """A log-distance floor of 30 × 24 m with 16 access points, surveyed every 6 m (5 scans
    per point), and single scans taken between the survey points (cell centres and edge
    midpoints) with their true positions."""
    site = make_site(nx=6, ny=5, spacing_m=SPACING, floors=(0,), n_wifi=16, n_ble=0, seed=seed, noise_db=1.0)
    survey = site.survey(scans_per_rp=5, seed=seed + 10, headings=())
    rng = np.random.default_rng(seed + 20)
    half = SPACING / 2
    pts = [(x + dx, y + dy) for x in np.arange(0, 30, SPACING) for y in np.arange(0, 24, SPACING)
           for dx, dy in ((half, half), (half, 0.0), (0.0, half))]
    return site, survey, [site.scan(x, y, 0, None, rng) for x, y in pts], np.array(pts)


def _mean_error(model, scans, truth) -> float:
    p = model.predict(scans)
    return float(np.hypot(p.x - truth[:, 0], p.y - truth[:, 1]).mean())


@pytest.fixture(scope="module")
def floor0():
    return _floor(0)


@pytest.fixture(scope="module")
def rmap0(floor0):
    return make_model("rmap").fit(floor0[1])


def test_between_survey_points_the_map_beats_knn_and_wknn():
    errors = {"knn": [], "wknn": [], "rmap": []}
    for seed in range(3):
        _, survey, scans, truth = _floor(seed)
        for name, e in errors.items():
            e.append(_mean_error(make_model(name).fit(survey), scans, truth))
    rmap, wknn, knn = (np.asarray(errors[n]) for n in ("rmap", "wknn", "knn"))
    assert np.all(rmap < wknn) and np.all(rmap < knn), errors
    assert rmap.mean() < 0.9 * min(wknn.mean(), knn.mean()), errors


def test_fixes_land_between_survey_points(floor0, rmap0):
    _, survey, scans, truth = floor0
    fixes = rmap0.locate_many(scans)
    surveyed = {(float(x), float(y)) for x, y in zip(survey.x, survey.y, strict=True)}
    off_survey = [(f.x, f.y) not in surveyed for f in fixes]
    assert np.mean(off_survey) > 0.5  # most answers are virtual cells, not surveyed points
    assert all(c.floor == 0 for f in fixes for c in f.candidates)
    assert len(rmap0.rp_xy_) > len(survey.reference_points())  # cells were added


def test_a_scan_at_a_surveyed_point_finds_it(floor0, rmap0):
    site, _, _, _ = floor0
    rng = np.random.default_rng(7)
    label, x, y, f = site.rp[12]
    fix = rmap0.locate(site.scan(x, y, f, None, rng, noise_db=0.5))
    assert fix.reference_point == label
    assert np.hypot(fix.x - x, fix.y - y) < 1.0


def test_choices_come_from_the_cross_validation(rmap0):
    assert rmap0.length_scale_m_ in rmap0.length_grid and rmap0.k_ in rmap0.k_grid
    errs = np.asarray(rmap0.cv_errors_)
    assert errs.shape == (len(rmap0.length_grid), len(rmap0.k_grid))
    i, j = rmap0.length_grid.index(rmap0.length_scale_m_), rmap0.k_grid.index(rmap0.k_)
    assert errs[i, j] == errs.min()
    assert rmap0.calibration_.scale != 1.0 or rmap0.calibration_.floor_m != 0.0  # calibrated on held-out fixes
    fixed = make_model("rmap", {"length_scale_m": 5.0, "k": 2, "calibrate": False}).fit(_floor(0)[1])
    assert (fixed.length_scale_m_, fixed.k_) == (5.0, 2) and not hasattr(fixed, "cv_errors_")


def test_training_step_reuses_the_validated_choices(floor0):
    model, v = fit_and_validate(lambda: make_model("rmap"), floor0[1], how="points")
    assert isinstance(model, RadioMapModel)
    assert model.length_scale_m == model.length_scale_m_ and model.k == model.k_  # taken, not chosen again
    assert model.calibration_ == v.calibration
    assert np.isfinite(v.metrics.mean_error_m)


def test_artifact_round_trip_answers_identically(floor0, rmap0):
    _, _, scans, _ = floor0
    blob = to_bytes(rmap0)
    assert len(blob) < 200_000  # the survey is stored, the map rebuilt
    loaded = from_bytes(blob)
    a, b = rmap0.predict(scans), loaded.predict(scans)
    for name in ("x", "y", "covariance", "top_rp", "top_p", "floor"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    fa, fb = rmap0.locate(scans[3]), loaded.locate(scans[3])
    assert (fa.x, fa.y, fa.reference_point) == (fb.x, fb.y, fb.reference_point)


def test_two_floors_answer_the_right_floor():
    site = make_site(nx=4, ny=3, spacing_m=SPACING, floors=(0, 1), n_wifi=8, n_ble=0, seed=3, noise_db=1.0)
    model = make_model("rmap").fit(site.survey(scans_per_rp=4, seed=4, headings=()))
    rng = np.random.default_rng(5)
    for f in (0, 1):
        fix = model.locate(site.scan(9.0, 3.0, f, None, rng))
        assert fix.floor == f and all(c.floor == f for c in fix.candidates)


@pytest.mark.parametrize("params", [
    {"length_scale_m": 0.0}, {"length_grid": ()}, {"length_grid": (2.0, -1.0)}, {"grid_m": 0.0},
    {"reach_m": -1.0}, {"k": 0}, {"k_grid": ()}, {"weight_power": 0.0}, {"cv_rows": 2}, {"missing": "nope"},
    {"spacing": 3.0},
])
def test_bad_params_are_value_errors(params):
    with pytest.raises(ValueError):
        make_model("rmap", params)
