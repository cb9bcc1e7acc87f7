"""What keeps training bounded: blockwise encoding, float32 training sets, capped stratified samples."""

from __future__ import annotations

import numpy as np

from server.estimation.fingerprint import FingerprintSet, features, make_model
from server.estimation.fingerprint.base import stratified_rows
from server.estimation.fingerprint.metrics import stratified_sample
from tests.helpers.synthetic import make_site


def test_blockwise_encoding_equals_one_pass(monkeypatch):
    rng = np.random.default_rng(0)
    rss = np.where(rng.random((50, 7)) < 0.4, np.nan, rng.uniform(-115, -20, (50, 7)))
    for missing in features.MISSING_MODES:
        enc = features.RssEncoder(missing)
        whole = enc.transform(rss)
        monkeypatch.setattr(features, "TRANSFORM_BLOCK_ROWS", 8)
        assert np.array_equal(enc.transform(rss), whole) and enc.transform(rss).dtype == np.float32
        monkeypatch.undo()


def test_a_float32_training_set_fits_like_a_float64_one():
    rows = make_site(nx=4, ny=3).survey(scans_per_rp=4, seed=0).to_rows()
    small, big = FingerprintSet.from_rows(rows, dtype=np.float32), FingerprintSet.from_rows(rows)
    assert small.rss.dtype == np.float32 and big.rss.dtype == np.float64
    assert small.subset(np.arange(5)).rss.dtype == np.float32
    a, b = make_model("knn").fit(small), make_model("knn").fit(big)
    scans = big.scans()[:10]
    assert np.allclose(a.predict(scans).xy, b.predict(scans).xy, atol=0.05)  # readings rounded to float32


def test_stratified_samples_keep_every_group_and_its_share():
    group = np.repeat([0, 1, 2], [900, 90, 10])
    rows = stratified_rows(group, 100)
    assert len(rows) <= 100 and len(np.unique(rows)) == len(rows)
    counts = np.bincount(group[rows], minlength=3)
    assert counts[0] == 90 and counts[1] == 9 and counts[2] == 1
    assert np.array_equal(stratified_rows(group, 5000), np.arange(1000))  # small enough: everything

    fs = make_site(nx=4, ny=3, floors=(0, 1, 2)).survey(scans_per_rp=10, seed=0)
    sample = stratified_sample(fs, 60)
    assert len(sample) <= 60 and set(sample.floor) == {0, 1, 2}
