"""Heading feature, transmitter kinds, missing-transmitter representations, data set."""

import numpy as np
import pytest

from server.estimation.fingerprint import (
    FingerprintSet,
    KNNModel,
    RssEncoder,
    UnknownTransmittersError,
    heading_features,
    make_model,
)
from server.estimation.fingerprint.dataset import group_split, random_split
from tests.helpers.synthetic import make_site

HEADING_ALGOS = ["wknn", "knn", "nbc", "kde", "tkbe", "svm"]


def _heading_twins():
    """Two reference points 20 m apart whose RSS is identical; they differ only in the
    heading they were surveyed with. Only the heading can tell them apart."""
    rng = np.random.default_rng(0)
    rows = []
    for lab, x, h in (("north", 0.0, 0.0), ("south", 20.0, 180.0)):
        for _ in range(6):
            rss = {"wifi:a": -60 + rng.normal(0, 1), "wifi:b": -70 + rng.normal(0, 1)}
            rows.append({"x": x, "y": 0.0, "floor": 0, "label": lab, "heading_deg": h, "rss": rss})
    return FingerprintSet.from_rows(rows)


@pytest.mark.parametrize("name", HEADING_ALGOS)
def test_heading_feature_separates_rps_that_rss_cannot(name):
    fs = _heading_twins()
    params = {"time_budget_s": 3.0} if name == "svm" else {}
    with_h = make_model(name, params, use_heading=True).fit(fs)
    scan = {"wifi:a": -60.0, "wifi:b": -70.0}
    assert with_h.locate(scan, heading_deg=5.0).reference_point == "north"
    assert with_h.locate(scan, heading_deg=175.0).reference_point == "south"
    without = make_model(name, params, use_heading=False).fit(fs)
    a = without.locate(scan, heading_deg=5.0)
    b = without.locate(scan, heading_deg=175.0)
    assert (a.x, a.y) == (b.x, b.y)  # heading ignored


def test_unknown_heading_is_neutral():
    h = heading_features([0.0, 90.0, None, np.nan])
    assert np.allclose(h[0], [0, 1]) and np.allclose(h[1], [1, 0], atol=1e-7)
    assert np.all(h[2:] == 0)
    fs = _heading_twins()
    m = KNNModel(k=12, weights="uniform", use_heading=True).fit(fs)
    fix = m.locate({"wifi:a": -60.0, "wifi:b": -70.0})  # no heading: both equally likely
    assert fix.x == pytest.approx(10.0, abs=1e-6)


def test_heading_helps_under_body_shadowing():
    site = make_site(seed=3, noise_db=1.5, body_loss_db=8.0, n_wifi=8, n_ble=0)
    train = site.survey(scans_per_rp=8, seed=1)
    test = site.survey(scans_per_rp=4, seed=2)
    err = {}
    for uh in (False, True):
        m = KNNModel(use_heading=uh).fit(train)
        p = m.predict(test, test.heading_deg)
        err[uh] = np.mean(np.hypot(p.x - test.x, p.y - test.y))
    assert err[True] < err[False]


def test_kinds_filter_transmitters():
    site = make_site(seed=1, noise_db=1.0)
    fs = site.survey(scans_per_rp=4, seed=0)
    ble = KNNModel(kinds=["ble"]).fit(fs)
    wifi = KNNModel(kinds=["wifi"]).fit(fs)
    assert ble.tx_ids_ and all(t.startswith("ble:") for t in ble.tx_ids_)
    assert wifi.tx_ids_ and all(t.startswith("wifi:") for t in wifi.tx_ids_)
    scan = site.scan(3, 3, 0, None, np.random.default_rng(1), noise_db=0)
    a = ble.locate(scan)
    scrambled = {t: (-30.0 if t.startswith("wifi:") else v) for t, v in scan.items()}
    b = ble.locate(scrambled)
    assert (a.x, a.y, a.floor) == (b.x, b.y, b.floor)  # wifi values do not matter
    with pytest.raises(UnknownTransmittersError):
        ble.locate({t: v for t, v in scan.items() if t.startswith("wifi:")})
    with pytest.raises(ValueError):
        KNNModel(kinds=["lora"]).fit(fs)


def test_missing_representations():
    floor = RssEncoder("floor", -110.0)
    powed = RssEncoder("powed", -110.0)
    r = np.array([[np.nan, -110.0, -120.0, -55.0, 0.0]])
    f, p = floor.transform(r)[0], powed.transform(r)[0]
    assert np.allclose(f, [0, 0, 0, 0.5, 1.0])  # not heard = floor value = 0
    assert np.allclose(p, [0, 0, 0, 0.5**np.e, 1.0], atol=1e-6)
    # powed compresses weak readings more than strong ones
    weak = powed.transform(np.array([[-100.0, -95.0]]))[0]
    strong = powed.transform(np.array([[-45.0, -40.0]]))[0]
    assert (weak[1] - weak[0]) < (strong[1] - strong[0])
    with pytest.raises(ValueError):
        RssEncoder("zero")


def _dropout_hits(missing, name, params):
    site = make_site(seed=5, noise_db=1.0, n_wifi=10, n_ble=4)
    fs = site.survey(scans_per_rp=6, seed=0)
    rng = np.random.default_rng(8)
    m = make_model(name, {"missing": missing, **params}).fit(fs)
    hits = 0
    for _label, x, y, f in site.rp:
        scan = site.scan(x, y, f, None, rng, noise_db=1.0)
        keep = sorted(scan, key=scan.get, reverse=True)[: max(3, len(scan) * 2 // 3)]  # weakest third lost
        fix = m.locate({t: scan[t] for t in keep})
        hits += fix.floor == f and np.hypot(fix.x - x, fix.y - y) < 3.5
    return hits / len(site.rp)


@pytest.mark.parametrize("name, params", [("knn", {"distance": "euclidean"}), ("nbc", {}), ("tkbe", {}), ("kde", {})])
def test_powed_survives_weak_transmitters_dropping_out(name, params):
    # A phone that misses its weakest readings: with the "floor" representation each
    # missing reading costs (rss − floor)², with "powed" weak readings cost little
    # (knn searches with Sørensen by default, which weighs a reading by its share of the scan).
    powed, floor = _dropout_hits("powed", name, params), _dropout_hits("floor", name, params)
    assert powed >= 0.9, powed
    assert powed > floor + 0.2, (powed, floor)


def test_fingerprint_set_from_rows_groups_reference_points():
    rows = [
        {"x": 1, "y": 2, "floor": 0, "rss": {"wifi:a": -50}, "label": "A"},
        {"x": 1.2, "y": 2, "floor": 0, "rss": {"wifi:a": -52, "ble:b": -70}, "label": "A"},
        {"x": 5, "y": 5, "floor": 0, "rss": {"ble:b": -60}},
        {"x": 5, "y": 5, "floor": 0, "rss": {"ble:b": -61}, "heading_deg": 90},
        {"x": 5, "y": 5, "floor": 1, "rss": {"ble:b": -80}},
    ]
    fs = FingerprintSet.from_rows(rows)
    assert fs.tx_ids == ["ble:b", "wifi:a"]
    assert np.isnan(fs.rss[0, 0]) and fs.rss[1, 0] == -70
    rp = fs.reference_points()
    assert len(rp) == 3  # A; (0,5,5); (1,5,5)
    assert rp.row_rp[0] == rp.row_rp[1] and rp.row_rp[2] == rp.row_rp[3] != rp.row_rp[4]
    assert rp.x[rp.row_rp[0]] == pytest.approx(1.1)  # RP position = mean of its rows
    assert np.isnan(fs.heading_deg[0]) and fs.heading_deg[3] == 90
    back = FingerprintSet.from_rows(fs.to_rows())
    assert np.array_equal(np.isnan(back.rss), np.isnan(fs.rss))
    assert fs.select_kinds(["wifi"]).tx_ids == ["wifi:a"]
    assert len(fs.drop_empty()) == 5
    al = fs.aligned_rss(["wifi:a", "wifi:zzz"])
    assert al.shape == (5, 2) and np.all(np.isnan(al[:, 1]))


def test_splits():
    site = make_site(seed=0)
    fs = site.survey(scans_per_rp=6, seed=0)
    tr, te, held = group_split(fs, "device", 0.3, seed=1)
    assert len(tr) + len(te) == len(fs)
    assert set(te.device) == set(held) and not set(te.device) & set(tr.device)
    tr2, te2 = random_split(fs, 0.25, seed=0)
    assert len(te2) == round(0.25 * len(fs))
