"""The held-out simulator's floor plan (``benchmarks/scenario_family.py --plan``) fits its walks:
every true position is walkable and no true step crosses a wall, while the loop's middle is not
walkable — so the figures measured with it judge the trackers, not an impossible plan."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.scenario_family import World, draw, walk
from server.estimation.tracking.geometry import crosses_walls


@pytest.mark.parametrize(("split", "index"), [("heldout", 0), ("heldout", 5), ("tune", 3), ("stress", 15)])
def test_the_loop_plan_holds_the_true_walk(split, index):
    world = World(draw(split, index))
    walls, walkable = world.plan(3.0)
    truth = walk(world).truth
    assert walkable.contains(truth).all()
    assert not crosses_walls(truth[:-1], truth[1:], np.asarray(walls, float)).any()
    W, H = world.sc.width_m, world.sc.height_m
    assert not walkable.contains(np.array([[W / 2, H / 2], [-3.0, -3.0]])).any()


def test_the_splits_draw_from_ranges_that_do_not_overlap():
    """stress is harsher than heldout (and heldout than tune) on every PDR and radio parameter,
    so a choice made on stress or tune is reported on heldout draws it never saw."""
    from benchmarks.scenario_family import RANGES

    harsher = ("drift_deg_per_step", "bias0_deg", "length_bias", "heading_white_deg", "scan_noise_db", "shadow_db",
               "gauss_fix_std_m")
    for easy, hard in (("tune", "heldout"), ("heldout", "stress")):
        for k in harsher:
            assert RANGES[easy][k][1] < RANGES[hard][k][0], (easy, hard, k)
        assert RANGES[hard]["n_tx"][1] < RANGES[easy]["n_tx"][0]  # fewer transmitters
    for i in range(8):
        sc = draw("stress", i)
        assert 0.28 <= abs(sc.drift_deg_per_step) <= 0.4 and sc.seed == 30_000 + i


def test_shared_fixes_share_their_error_along_the_walk_as_declared():
    """``--fixes shared``: each fix's error has the declared marginal variance σ²I, and fixes a few
    metres apart share most of it (the real walks' property the simulator's knn fixes lack), while
    ``--fixes gaussian`` fixes share nothing."""
    from benchmarks.fix_correlation import band_sums, correlation, pair_distances, walk_errors
    from benchmarks.scenario_family import GaussianFixes, SharedFixes

    near = {}
    for kind in (SharedFixes, GaussianFixes):
        sums, squares, count = np.zeros((6, 4)), 0.0, 0
        for index in range(12):
            sc = draw("heldout", index)
            w = walk(World(sc))
            fixes = kind(w, sc.gauss_fix_std_m, sc.seed + 4)
            xy = np.array([fixes.by_t[s.t] for s in w.scans])
            err, white, walked = walk_errors(xy, np.array([fixes.cov] * len(xy)), w.scan_truth)
            sums += band_sums(white, pair_distances(w.scan_truth, walked, "walked"))
            squares, count = squares + float((white**2).sum()), count + len(white)
        assert squares / count == pytest.approx(2.0, rel=0.25)  # E|whitened error|² = 2 in 2-D
        near[kind] = correlation(sums)[1]  # fixes 2–5 m apart
    assert near[GaussianFixes] == pytest.approx(0.0, abs=0.1)
    # ≈ SHARED_WALK + SHARED_DECAYING·e^(−3.5 m / 8 m) ≈ 0.68 expected; the simulator's knn fixes: ≤ 0.25
    assert near[SharedFixes] > 0.5


def test_fix_pairs_are_apart_by_distance_walked_or_by_place():
    """A walker who goes 10 m out and comes back: the first and last fixes are 20 m apart by
    the distance walked and 0 m apart by place."""
    from benchmarks.fix_correlation import band_sums, pair_distances
    from benchmarks.scenario_family import distance_walked

    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 0.0]])
    walked = distance_walked(truth)
    np.testing.assert_allclose(pair_distances(truth, walked, "walked"), [10.0, 20.0, 10.0])  # (0,1) (0,2) (1,2)
    np.testing.assert_allclose(pair_distances(truth, walked, "place"), [10.0, 0.0, 10.0])
    err = np.array([[1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]])  # the first and last fixes share their error
    by_place = band_sums(err, pair_distances(truth, walked, "place"))
    assert by_place[0, 0] == 1.0 and by_place[0, 3] == 1  # 0–2 m: the (0, 2) pair, e·e = 1
    assert band_sums(err, pair_distances(truth, walked, "walked"))[0, 3] == 0


def test_client_sim_walks_give_each_scan_its_fix_and_truth():
    """``fix_correlation.py --client-sim``: every located scan of a walk has a fix, a positive definite
    calibrated covariance and the walker's true position at that time, in walking order; the fixes'
    whitened error has E|w|² of the order of 2 (the model is calibrated on the survey's held-out points)."""
    from benchmarks.fix_correlation import client_sim_walks, walk_errors

    walks = list(client_sim_walks("open_room", 2, "knn"))
    assert len(walks) == 2
    white_sq, n = 0.0, 0
    for fixes, covariances, truth in walks:
        assert fixes.shape == truth.shape and len(fixes) > 50 and covariances.shape == (len(fixes), 2, 2)
        assert np.all(np.linalg.eigvalsh(covariances) > 0)
        err, white, walked = walk_errors(fixes, covariances, truth)
        assert np.all(np.diff(walked) >= 0) and walked[-1] > 20.0
        white_sq, n = white_sq + float((white**2).sum()), n + len(white)
    assert 0.5 < white_sq / n < 8.0
