"""Every fingerprint algorithm on a small synthetic two-floor site where the answer is known."""

import numpy as np
import pytest

from server.estimation.fingerprint import (
    ALGORITHMS,
    FingerprintSet,
    KDEModel,
    KNNModel,
    UnknownTransmittersError,
    evaluate,
    make_model,
)
from server.estimation.types import Fix
from tests.helpers.synthetic import make_site

FAST = {"svm": {"time_budget_s": 5.0, "C": 10.0}}


@pytest.fixture(scope="module")
def site():
    return make_site(seed=1, noise_db=1.5)


@pytest.fixture(scope="module")
def survey(site):
    return site.survey(scans_per_rp=6, seed=2)


def _model(name, site, **kw):
    params = dict(FAST.get(name, {}))
    if name == "propagation":
        params["transmitters"] = site.transmitters
    params.update(kw)
    return make_model(name, params)


@pytest.fixture(scope="module")
def fitted(site, survey):
    return {name: _model(name, site).fit(survey) for name in ALGORITHMS}


def _queries(site, n_per_rp=2, seed=5, noise=1.0):
    rng = np.random.default_rng(seed)
    out = []
    for label, x, y, f in site.rp:
        for _ in range(n_per_rp):
            out.append((label, x, y, f, site.scan(x, y, f, None, rng, noise_db=noise)))
    return out


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_scan_at_reference_point_maps_back_with_right_floor(name, site, fitted):
    model = fitted[name]
    qs = _queries(site)
    fixes = model.locate_many([q[4] for q in qs])
    floors = np.array([fx.floor for fx in fixes])
    truth_floor = np.array([q[3] for q in qs])
    assert np.all(floors == truth_floor), f"{name}: wrong floor"
    err = np.array([np.hypot(fx.x - q[1], fx.y - q[2]) for fx, q in zip(fixes, qs, strict=True)])
    mapped = np.mean([fx.reference_point == q[0] for fx, q in zip(fixes, qs, strict=True)])
    if name == "propagation":  # no fingerprint matching: a looser bound
        assert err.mean() < 2.5
    else:
        assert err.mean() < 1.2, f"{name}: mean error {err.mean():.2f}"
        assert mapped >= 0.7, f"{name}: mapping rate {mapped:.2f}"


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_fix_is_consistent(name, site, fitted):
    model = fitted[name]
    label, x, y, f, scan = _queries(site, n_per_rp=1, seed=9)[7]
    fix = model.locate(scan)
    assert isinstance(fix, Fix)
    cov = np.asarray(fix.covariance)
    assert cov.shape == (2, 2) and np.allclose(cov, cov.T)
    floor2 = model.calibration_.apply(np.diag([model.cov_floor_m_**2] * 2)[None])[0, 0, 0]  # calibrated models scale it
    assert np.all(np.linalg.eigvalsh(cov) >= floor2 - 1e-9)  # floored
    assert fix.candidates, "candidates expected"
    probs = [c.probability for c in fix.candidates]
    assert probs == sorted(probs, reverse=True) and sum(probs) <= 1 + 1e-9
    assert all(c.floor == fix.floor for c in fix.candidates)  # never another floor
    assert fix.reference_point == fix.candidates[0].label
    # locate and locate_many agree
    many = model.locate_many([scan])[0]
    assert np.allclose([many.x, many.y], [fix.x, fix.y]) and many.floor == fix.floor


def test_position_never_from_wrong_floor(site, survey):
    # A scan midway between floors in signal terms still yields a position that is a
    # mixture of reference points of the single floor reported.
    model = KNNModel(k=6, floor_k=6).fit(survey)
    rng = np.random.default_rng(3)
    s0 = site.scan(6, 3, 0, None, rng, noise_db=0)
    s1 = site.scan(6, 3, 1, None, rng, noise_db=0)
    mixed = {t: max(s0.get(t, -200), s1.get(t, -200)) for t in set(s0) | set(s1)}
    fix = model.locate(mixed)
    assert all(c.floor == fix.floor for c in fix.candidates)
    assert fix.floor in (0, 1)


def test_unknown_transmitters_raise(fitted):
    with pytest.raises(UnknownTransmittersError):
        fitted["knn"].locate({"wifi:nobody": -50.0})


def test_knn_weights_and_k():
    # three RPs on a line; the query's Sørensen distance (|q − f| / (q + f) over RSS above the
    # −110 dBm floor) to b is 10/90, to c 10/70, to a 30/110: b and c are the two nearest, and
    # distance weighting pulls towards b (no per-query offset estimate: one transmitter cannot
    # tell an offset from a place)
    rows = []
    for lab, x, v in (("a", 0.0, -40.0), ("b", 10.0, -60.0), ("c", 20.0, -80.0)):
        rows.append({"x": x, "y": 0.0, "floor": 0, "label": lab, "rss": {"wifi:t": v}})
    fs = FingerprintSet.from_rows(rows)
    q = {"wifi:t": -70.0}
    uni = KNNModel(k=2, weights="uniform", missing="floor", offset_estimate=False).fit(fs).locate(q)
    dist = KNNModel(k=2, weights="distance", missing="floor", offset_estimate=False).fit(fs).locate(q)
    assert uni.x == pytest.approx(15.0)  # plain mean of b and c
    assert 10.0 < dist.x < 15.0  # b weighted more
    one = KNNModel(k=1).fit(fs).locate(q)
    assert one.reference_point == "b" and one.x == pytest.approx(10.0)


def test_spatial_restriction_for_tracking(site, survey):
    model = KDEModel().fit(survey)
    rng = np.random.default_rng(4)
    scan = site.scan(0, 0, 0, None, rng, noise_db=1.0)
    free = model.locate(scan)
    assert np.hypot(free.x, free.y) < 2.0
    near = model.locate(scan, near=(12.0, 9.0, 0), radius_m=4.0)
    assert all(np.hypot(c.x - 12, c.y - 9) <= 4.0 + 1e-9 for c in near.candidates)
    assert np.hypot(near.x - 12, near.y - 9) <= 4.0
    assert near.floor == 0


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_every_algorithm_keeps_a_tracking_sessions_fix_inside_its_search_circle(name, site, fitted):
    """A self-calibrating session asks every fix with ``near=(x, y)`` (no floor) and a radius: the
    answer stays inside however much the scan resembles somewhere else."""
    scan = site.scan(0, 0, 0, None, np.random.default_rng(4), noise_db=1.0)
    fix = fitted[name].locate(scan, near=(12.0, 9.0), radius_m=4.0)
    assert fix.candidates
    assert all(np.hypot(c.x - 12, c.y - 9) <= 4.0 + 1e-9 for c in fix.candidates)
    assert np.hypot(fix.x - 12, fix.y - 9) <= 4.0 + 1e-9


def test_covariance_reflects_ambiguity(site, survey):
    model = KDEModel().fit(survey)
    rng = np.random.default_rng(6)
    clean = model.locate(site.scan(6, 3, 0, None, rng, noise_db=0.5))
    blurred = model.locate(site.scan(6, 3, 0, None, rng, noise_db=12.0), near=None)
    assert np.trace(clean.covariance) <= np.trace(blurred.covariance) + 1e-9


def test_metrics_on_held_out(site, survey):
    model = KNNModel().fit(survey)
    test = site.survey(scans_per_rp=2, seed=11, headings=())
    m = evaluate(model, test, n_single=20)
    assert m.floor_hit_rate == 1.0
    assert m.mapping_rate > 0.7
    assert m.mean_error_m < 1.2 and m.p50_error_m <= m.p90_error_m
    assert m.fit_time_s > 0 and m.us_per_query > 0 and m.single_query_us > 0
    assert set(m.as_api_dict()) == {"mean_error_m", "p50_error_m", "p90_error_m", "mapping_rate", "floor_hit_rate"}


def test_registry_rejects_unknown_names():
    with pytest.raises(ValueError):
        make_model("nope")
    with pytest.raises(ValueError):
        make_model("knn", {"kk": 3})
    m = make_model("knn", {"k": 5}, use_heading=True, kinds=["wifi"])
    assert m.k == 5 and m.use_heading and m.kinds == ["wifi"]
    assert {"nbc", "knn", "svm", "kde", "tkbe", "propagation"} <= set(ALGORITHMS)


@pytest.mark.parametrize("algorithm, params", [
    ("knn", {"k": 0}), ("knn", {"k": -2}), ("knn", {"floor_k": 0}), ("tkbe", {"n_preselect": 0}),
    ("wknn", {"k": 0}), ("wknn", {"building_k": 0}), ("wknn", {"floor_k": -1}), ("wknn", {"k_grid": [0, 3]}),
    ("wknn", {"k_grid": []}),
])
def test_neighbour_counts_below_one_are_refused(algorithm, params):
    """(They used to fit, and answer the centroid of the site for every scan.)"""
    with pytest.raises(ValueError, match="at least 1"):
        make_model(algorithm, params)


@pytest.mark.parametrize("clf", ["svc", "trees"])
def test_dedicated_floor_classifier(clf, site, survey):
    model = KNNModel(floor_classifier=clf).fit(survey)
    qs = _queries(site, n_per_rp=1, seed=12)
    fixes = model.locate_many([q[4] for q in qs])
    assert all(fx.floor == q[3] for fx, q in zip(fixes, qs, strict=True))
    assert all(c.floor == fx.floor for fx in fixes for c in fx.candidates)
    with pytest.raises(ValueError):
        KNNModel(floor_classifier="magic")


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_tiny_sites_train_and_answer(name):
    # one scan per floor, no headings: every algorithm must still train and answer
    rows = [{"x": 1, "y": 1, "floor": 0, "rss": {"wifi:a": -50}},
            {"x": 5, "y": 1, "floor": 1, "rss": {"wifi:a": -80, "ble:b": -60}}]
    fs = FingerprintSet.from_rows(rows)
    params = {"time_budget_s": 1.0} if name == "svm" else {}
    for uh in (False, True):
        m = make_model(name, params, use_heading=uh).fit(fs)
        fix = m.locate({"wifi:a": -52.0}, heading_deg=30.0)
        assert fix.floor == 0 and (fix.x, fix.y) == (1.0, 1.0)
        assert m.locate({"ble:b": -61.0, "wifi:a": -79.0}).floor == 1
