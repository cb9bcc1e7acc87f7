"""The shared (building, floor) classifier (``floor_classifier``) on a synthetic campus:
two buildings of three floors each, held-out scans, a phone reading 8 dB quieter."""

import numpy as np
import pytest

from server.estimation.fingerprint import FingerprintSet, KNNModel, from_bytes, make_model, to_bytes
from server.estimation.fingerprint.base import FLOOR_CLASSIFIERS, FloorKNN
from tests.helpers.synthetic import make_site, with_prefix

#: building → its floor levels (building 1's differ, so a floor of the wrong building shows)
FLOORS = {0: (0, 1, 2), 1: (1, 2, 3)}
CLASSIFIERS = [c for c in FLOOR_CLASSIFIERS if c is not None]


@pytest.fixture(scope="module")
def campus():
    """Two buildings 60 m apart with their own transmitters; building 1's scans also hear
    one of building 0's access points weakly."""
    sites = {b: with_prefix(make_site(floors=FLOORS[b], n_wifi=9, n_ble=3, seed=20 + b, noise_db=2.0), f"b{b}")
             for b in FLOORS}
    leak = sites[0].transmitters[0]["id"]
    rows = []
    for b, site in sites.items():
        for r in site.survey(scans_per_rp=4, seed=30 + b, headings=None).to_rows():
            r["building"], r["label"], r["x"] = b, f"b{b}-{r['label']}", r["x"] + 60.0 * b
            if b == 1:
                r["rss"][leak] = -95.0
            rows.append(r)
    return sites, leak, FingerprintSet.from_rows(rows)


def _held_out(sites, leak, shift_db=0.0, seed=7):
    """Fresh scans (noise 3 dB) at every reference point of both buildings, each reading
    shifted by ``shift_db``; building 1's hear building 0's access point at −75 dBm."""
    rng = np.random.default_rng(seed)
    scans, truth = [], []
    for b, site in sites.items():
        for _, x, y, f in site.rp:
            s = site.scan(x, y, f, None, rng, noise_db=3.0)
            if b == 1:
                s[leak] = -75.0
            scans.append({t: v + shift_db for t, v in s.items()})
            truth.append((b, f))
    return scans, np.array(truth)


@pytest.fixture(scope="module")
def models(campus):
    return {c: KNNModel(floor_classifier=c).fit(campus[2]) for c in CLASSIFIERS}


@pytest.mark.parametrize("clf", CLASSIFIERS)
def test_held_out_scans_get_their_building_and_floor(clf, campus, models):
    sites, leak, _ = campus
    scans, truth = _held_out(sites, leak)
    pred = models[clf].predict(scans)
    assert np.all(pred.building == truth[:, 0]), clf
    assert np.mean(pred.floor == truth[:, 1]) >= 0.97, clf


@pytest.mark.parametrize("clf", ["knn", "knn-svc"])
def test_a_phone_8_db_quieter_keeps_building_and_floor(clf, campus, models):
    sites, leak, _ = campus
    scans, truth = _held_out(sites, leak, shift_db=-8.0)
    pred = models[clf].predict(scans)
    assert np.all(pred.building == truth[:, 0]), clf
    assert np.mean(pred.floor == truth[:, 1]) >= 0.97, clf


def test_knn_features_do_not_depend_on_a_constant_offset(campus, models):
    """Exponential features divided by their sum: a shift of every reading (none crossing
    the −110 dBm floor) gives the same distances to every reference point."""
    sites, leak, _ = campus
    model = models["knn"]
    scans, _ = _held_out(sites, leak, seed=3)
    R = model.scan_matrix(scans)
    clf = model.floor_clf_
    assert isinstance(clf, FloorKNN)
    d0 = clf.distances(model.encoder_.transform(R))
    d8 = clf.distances(model.encoder_.transform(R - 8.0))
    assert np.allclose(d0, d8, atol=1e-5)


@pytest.mark.parametrize("clf", CLASSIFIERS)
def test_building_and_floor_are_always_a_pair_of_the_site(clf, campus, models):
    sites, leak, fs = campus
    scans, _ = _held_out(sites, leak, seed=11)
    weird = [{k: v - 20.0 for k, v in s.items()} for s in scans[::5]]  # far from everything surveyed
    pred = models[clf].predict(scans + weird)
    pairs = {(b, f) for b in FLOORS for f in FLOORS[b]}
    assert {(int(b), int(f)) for b, f in zip(pred.building, pred.floor, strict=True)} <= pairs
    fixes = models[clf].locate_many(scans[:10])
    assert all(c.building == fx.building and c.floor == fx.floor for fx in fixes for c in fx.candidates)


def test_knn_keeps_one_row_per_reference_point(campus, models):
    """Fitted state per reference point, not per fingerprint: four times the scans, same size."""
    _, _, fs = campus
    many = FingerprintSet.from_rows(fs.to_rows() * 4)
    a, b = models["knn"].floor_clf_, KNNModel(floor_classifier="knn").fit(many).floor_clf_
    assert a.MT_.shape == b.MT_.shape == (len(fs.tx_ids), len(fs.reference_points().keys))
    assert np.allclose(a.MT_, b.MT_, atol=1e-6)


@pytest.mark.parametrize("clf", ["knn", "knn-svc"])
def test_artifact_round_trip_answers_the_same(clf, campus, models):
    sites, leak, _ = campus
    scans, _ = _held_out(sites, leak, seed=5)
    model = models[clf]
    back = from_bytes(to_bytes(model))
    assert isinstance(back.floor_clf_, FloorKNN)
    p, q = model.predict(scans), back.predict(scans)
    assert np.array_equal(p.floor, q.floor) and np.array_equal(p.building, q.building)
    assert np.allclose(p.xy, q.xy)


@pytest.mark.parametrize("bad", ["magic", "SVC", "", "hgb", 3])
def test_bad_option_values_raise(bad):
    with pytest.raises(ValueError):
        KNNModel(floor_classifier=bad)
    with pytest.raises(ValueError):
        make_model("kde", {"floor_classifier": bad})


def test_bad_row_cap_raises():
    with pytest.raises(ValueError):
        KNNModel(floor_classifier_rows=0)


def test_knn_svc_votes_as_the_svc_and_only_among_the_allowed_groups(campus, models):
    """FloorKNN's NumPy one-vs-one vote: scikit-learn's predict when every group is allowed;
    restricted to a building, always one of its groups."""
    from sklearn.svm import SVC

    sites, leak, fs = campus
    model = models["knn-svc"]
    X = model.encoder_.transform(fs.aligned_rss(model.tx_ids_))
    row_group = model.rp_group_[model.rp_.row_rp]
    svc = SVC(C=10.0, gamma="scale").fit(X, row_group)
    clf = FloorKNN(model.encoder_, X.shape[1]).fit(X, model.rp_.row_rp, model.rp_group_, model.group_building_, svc=svc)
    scans, truth = _held_out(sites, leak, shift_db=-12.0, seed=17)  # a harder case: more disagreements
    Q = model.encoder_.transform(model.scan_matrix(scans))
    n_groups = len(model.group_floor_)
    every = np.ones((len(Q), n_groups), dtype=bool)
    assert np.array_equal(clf.svc_groups(Q, every), svc.predict(Q))
    one_by_one = [clf.svc_groups(Q[i: i + 1], every[i: i + 1])[0] for i in range(len(Q))]  # a session's path
    assert np.array_equal(one_by_one, svc.predict(Q))
    for b in FLOORS:
        allowed = np.tile(model.group_building_ == b, (len(Q), 1))
        assert np.all(model.group_building_[clf.svc_groups(Q, allowed)] == b)
    one = np.zeros((len(Q), n_groups), dtype=bool)
    one[:, 2] = True
    assert np.all(clf.svc_groups(Q, one) == 2)
