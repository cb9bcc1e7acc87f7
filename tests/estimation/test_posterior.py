"""``reduce_live``: the reduction over the live reference points (and of one query, written
out) is the full reduction."""

import numpy as np
import pytest

from server.estimation.fingerprint.posterior import reduce_live, reduce_posterior

N_RP = 60


def _site(seed: int):
    rng = np.random.default_rng(seed)
    rp_xy = rng.uniform(0, 50, (N_RP, 2))
    rp_group = rng.integers(0, 4, N_RP)
    return rp_xy, rp_group, np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])


def _knn_logs(seed: int, n: int, k: int) -> np.ndarray:
    """A k-NN's log-scores: k finite entries per query, −inf elsewhere."""
    rng = np.random.default_rng(seed)
    logs = np.full((n, N_RP), -np.inf)
    for row in logs:
        row[rng.choice(N_RP, k, replace=False)] = np.log(rng.uniform(0.1, 1.0, k))
    return logs


def _same(a, b):
    """Same floor, building, moments and candidates with probability (those a fix reports)."""
    assert np.array_equal(a.floor, b.floor) and np.array_equal(a.building, b.building)
    assert np.allclose(a.x, b.x, rtol=0, atol=1e-12) and np.allclose(a.y, b.y, rtol=0, atol=1e-12)
    assert np.allclose(a.covariance, b.covariance, rtol=1e-12, atol=1e-9)
    assert np.array_equal(a.best_rp, b.best_rp)
    for i in range(len(a)):
        live_a = {(int(r), round(float(p), 12)) for r, p in zip(a.top_rp[i], a.top_p[i], strict=True) if p > 0}
        live_b = {(int(r), round(float(p), 12)) for r, p in zip(b.top_rp[i], b.top_p[i], strict=True) if p > 0}
        assert live_a == live_b
    assert a.top_rp.shape == b.top_rp.shape


@pytest.mark.parametrize(("n", "k"), [(1, 3), (1, 9), (1, N_RP), (7, 3), (20, 12)])
def test_live_columns_reduce_as_every_column(n, k):
    rp_xy, rp_group, floor, building = _site(n + k)
    logs = _knn_logs(100 + n, n, k)
    _same(reduce_live(logs, rp_xy, rp_group, floor, building, 2.0), reduce_posterior(logs, rp_xy, rp_group, floor,
                                                                                     building, 2.0))


def test_a_query_without_weight_takes_the_full_reduction():
    """A query giving weight to no reference point: uniform over the first group's points, as
    over every column (the restriction would have left that query nothing to average)."""
    rp_xy, rp_group, floor, building = _site(5)
    logs = _knn_logs(6, 3, 3)
    logs[1] = -np.inf
    live = reduce_live(logs, rp_xy, rp_group, floor, building, 2.0)
    full = reduce_posterior(logs, rp_xy, rp_group, floor, building, 2.0)
    assert np.all(np.isfinite(live.covariance))
    _same(live, full)
    assert np.allclose(live.xy[1], rp_xy[rp_group == 0].mean(axis=0))
