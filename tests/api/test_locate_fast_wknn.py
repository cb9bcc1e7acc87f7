"""wknn's per-query shortcuts answer bit for bit as the computations they replace: the
intersections over the float32 transmitter index, the offset estimate's neighbours taken from
the hierarchy's partial sort (ties included), the median, and the groups' unique/inverse."""

from __future__ import annotations

import numpy as np
import pytest

from server.estimation.fingerprint import make_model
from server.estimation.fingerprint.posterior import unique_inverse
from server.estimation.fingerprint.wknn import _smallest
from tests.helpers.synthetic import make_site


@pytest.fixture(scope="module")
def site_and_model():
    site = make_site(nx=7, ny=5, seed=4, noise_db=2.0)
    fs = site.survey(scans_per_rp=6, seed=1)
    return site, make_model("wknn").fit(fs)


def _queries(site, model, n: int = 40) -> np.ndarray:
    rng = np.random.default_rng(3)
    scans = []
    for i, (_, x, y, f) in enumerate(site.rp):
        s = site.scan(x, y, f, None, rng)
        scans.append({t: v + (7.0 if i % 3 == 0 else 0.0) for t, v in s.items()})  # some shifted: offset loop
    return model.encoder_.transform(model.scan_matrix(scans[:n]))


def test_intersections_are_the_dense_column_order_sums(site_and_model):
    site, model = site_and_model
    assert model.tx_vals_.dtype == np.float32
    F = model.XT_.astype(np.float64)
    for q in _queries(site, model):
        q = q * model.tx_active_
        cols = np.flatnonzero(q > 0)
        dense = np.zeros(F.shape[1])
        for j in cols:  # column by column, in float64, as the index accumulates them
            dense += np.minimum(F[j], np.float64(q[j]))
        assert np.array_equal(model._intersections(cols, q[cols]), dense)


def _offset_as_before(model, q, cand, d) -> float:
    """The estimate as it was computed before it shared the hierarchy's partial sort."""
    k = max(1, min(model.offset_neighbours, model.XT_.shape[1]))
    near = cand[_smallest(d, k)]
    cols = np.flatnonzero(q > 0)
    diff = model.encoder_.decode(model.XT_[np.ix_(cols, near)].T) - model.encoder_.decode(q[cols][None])
    diff = diff[~np.isnan(diff)]
    return float(np.clip(np.median(diff), -model.offset_max_db, model.offset_max_db)) if len(diff) >= 3 else 0.0


def test_the_offset_estimate_from_the_shared_partial_sort_is_the_one_from_its_own(site_and_model):
    site, model = site_and_model
    for q in _queries(site, model):
        cand, d = model._query_distances(q, None)
        near = model._sorted_nearest(d)
        assert near is not None
        expected = _offset_as_before(model, q, cand, d)
        assert model._estimate_offset(q, cand, d, near) == expected
        assert model._estimate_offset(q, cand, d) == expected
        tied = d.copy()  # a tie across the k-th neighbour: the partial sort picks, as it always did
        k = model.offset_neighbours
        tied[near[k]] = tied[near[k - 1]]
        assert model._estimate_offset(q, cand, tied, model._sorted_nearest(tied)) == \
            _offset_as_before(model, q, cand, tied)


def test_one_query_path_answers_as_each_step_did(site_and_model):
    """The shared partial sort changes nothing downstream: scores and coverage as from fresh sorts."""
    site, model = site_and_model
    for q in _queries(site, model):
        cand, d, near = model._offset_query_nearest(q, None)
        c2, d2 = model._offset_query(q, None)
        assert np.array_equal(cand, c2) and np.array_equal(d, d2)
        assert model._coverage_distance(cand, d, near) == model._coverage_distance(cand, d)
        assert np.array_equal(model._query_scores(cand, d, None, near), model._query_scores(cand, d, None))


@pytest.mark.parametrize("values", [[3], [5, 1, 5, 2, 1], [0, 0, 0], [9, 4, 7, 4, 9, 0, 12]])
def test_unique_inverse_is_numpys(values):
    a = np.array(values, dtype=np.int64)
    groups, inverse = unique_inverse(a)
    expected_groups, expected_inverse = np.unique(a, return_inverse=True)
    assert np.array_equal(groups, expected_groups) and groups.dtype == expected_groups.dtype
    assert np.array_equal(inverse, expected_inverse.reshape(-1))
