"""`FingerprintSet.from_rows` reads rows once (an iterator is never listed) into a float16 matrix
when every reading is exactly one, float32 otherwise: the same values, the same fitted models."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from server.estimation.fingerprint import FingerprintSet, make_model
from tests.helpers.synthetic import make_site

ROWS = [
    {"x": 1, "y": 2, "floor": 0, "rss": {"wifi:b": -50, "wifi:a": None}, "label": "A", "device": "p1"},
    {"x": 1.5, "y": 2, "floor": 1, "rss": {"ble:z": -71.5, "wifi:b": -60}, "label": "", "t": 3.0, "building": 2},
    {"x": 4, "y": 5, "floor": 0, "rss": {}, "heading_deg": 90.0, "user": "u", "device": "p1"},
]


def once(rows: list[dict]) -> Iterator[dict]:
    """The rows as a stream that can be read only once (a consumer listing it would find it empty)."""
    yield from rows


def test_a_stream_of_rows_builds_the_set_column_by_column():
    fs = FingerprintSet.from_rows(once(ROWS))
    assert fs.tx_ids == ["ble:z", "wifi:a", "wifi:b"]  # sorted, including an id heard only as None
    assert fs.rss.dtype == np.float64
    assert np.array_equal(fs.rss, [[np.nan, np.nan, -50], [-71.5, np.nan, -60], [np.nan] * 3], equal_nan=True)
    assert fs.x.tolist() == [1, 1.5, 4] and fs.floor.tolist() == [0, 1, 0] and fs.building.tolist() == [0, 2, 0]
    assert list(fs.label) == ["A", None, None] and list(fs.device) == ["p1", None, "p1"]
    assert list(fs.user) == [None, None, "u"]
    assert np.array_equal(fs.t, [np.nan, 3.0, np.nan], equal_nan=True)
    assert np.array_equal(fs.heading_deg, [np.nan, np.nan, 90.0], equal_nan=True)
    bare = FingerprintSet.from_rows(once([{"x": 0, "y": 0, "floor": 0, "rss": {"wifi:a": -1}}]))
    assert bare.user is None and bare.device is None and bare.t is None and bare.building.tolist() == [0]
    given = FingerprintSet.from_rows(once(ROWS), tx_ids=["wifi:b", "wifi:new"])
    assert given.tx_ids == ["wifi:b", "wifi:new"]  # ids outside tx_ids dropped
    assert np.array_equal(given.rss, [[-50, np.nan], [-60, np.nan], [np.nan, np.nan]], equal_nan=True)
    empty = FingerprintSet.from_rows(once([]), dtype=np.float16)
    assert len(empty) == 0 and empty.rss.shape == (0, 0)


def test_float16_only_when_every_reading_is_exact_and_then_equal_to_float32():
    whole = [{**r, "rss": {k: v for k, v in r["rss"].items() if v != -71.5}} for r in ROWS]
    assert FingerprintSet.from_rows(once(whole), dtype=np.float16).rss.dtype == np.float16
    half_db = FingerprintSet.from_rows(once(ROWS), dtype=np.float16)  # -71.5 is a float16 too
    assert half_db.rss.dtype == np.float16
    odd = [*ROWS, {"x": 0, "y": 0, "floor": 0, "rss": {"wifi:a": -67.3}}]
    fallback, f32 = FingerprintSet.from_rows(once(odd), dtype=np.float16), FingerprintSet.from_rows(odd, dtype=np.float32)
    assert fallback.rss.dtype == np.float32 and np.array_equal(fallback.rss, f32.rss, equal_nan=True)
    assert np.array_equal(half_db.rss.astype(np.float32), FingerprintSet.from_rows(ROWS, dtype=np.float32).rss,
                          equal_nan=True)
    assert half_db.subset([0, 1]).rss.dtype == np.float16
    assert half_db.select_kinds(["wifi"]).rss.dtype == np.float16  # kinds keep the compact matrix


@pytest.mark.parametrize("algorithm", ["wknn", "knn"])
def test_a_float16_training_set_fits_exactly_like_a_float32_one(algorithm):
    rows = make_site(nx=4, ny=3, floors=(0, 1)).survey(scans_per_rp=4, seed=0).to_rows()
    for r in rows:  # phones report whole dBm
        r["rss"] = {k: float(round(v)) for k, v in r["rss"].items()}
    small, f32 = FingerprintSet.from_rows(once(rows), dtype=np.float16), FingerprintSet.from_rows(rows, dtype=np.float32)
    assert small.rss.dtype == np.float16 and small.rss.nbytes * 2 == f32.rss.nbytes
    a, b = make_model(algorithm).fit(small), make_model(algorithm).fit(f32)
    scans = f32.scans()[::5]
    pa, pb = a.predict(scans), b.predict(scans)
    assert np.array_equal(pa.xy, pb.xy) and np.array_equal(pa.covariance, pb.covariance)


def test_blocks_of_rows_fill_the_same_matrix(monkeypatch):
    from server.estimation.fingerprint import dataset

    odd = [*ROWS, {"x": 0, "y": 0, "floor": 0, "rss": {"wifi:a": -67.3, "wifi:c": -80}}]
    whole = {dt: FingerprintSet.from_rows(odd, dtype=dt) for dt in (float, np.float16)}
    monkeypatch.setattr(dataset, "FILL_ROWS", 2)
    monkeypatch.setattr(dataset, "FILL_READINGS", 3)  # the reading that is no float16 is in the last check
    for dt, fs in whole.items():
        blocks = FingerprintSet.from_rows(once(odd), dtype=dt)
        assert blocks.rss.dtype == fs.rss.dtype and np.array_equal(blocks.rss, fs.rss, equal_nan=True)
    assert whole[np.float16].rss.dtype == np.float32
