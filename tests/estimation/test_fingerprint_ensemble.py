"""The ensemble model ("ensemble"): floor vote, combined positions and covariance, artifact."""

import numpy as np
import pytest

from server.estimation.fingerprint import Prediction, fit_and_validate, from_bytes, make_model, to_bytes
from server.estimation.fingerprint.ensemble import DEFAULT_MEMBERS, EnsembleModel, vote_groups
from tests.helpers.synthetic import make_site

MEMBERS = [{"algorithm": "wknn", "params": {"missing": "floor"}},
           {"algorithm": "wknn", "params": {"missing": "powed", "distance": "euclidean"}},
           {"algorithm": "knn", "params": {"k": 2}}]


@pytest.fixture(scope="module")
def site():
    return make_site(nx=6, ny=4, seed=7, noise_db=2.0)


@pytest.fixture(scope="module")
def survey(site):
    return site.survey(scans_per_rp=4, seed=1)


@pytest.fixture(scope="module")
def scans(site):
    """Noisy scans between reference points, so the members disagree."""
    rng = np.random.default_rng(3)
    out = []
    for _ in range(60):
        f = int(rng.integers(0, 2))
        out.append(site.scan(float(rng.uniform(0, 15)), float(rng.uniform(0, 9)), f, None, rng, noise_db=14.0))
    return out


@pytest.fixture(scope="module")
def model(survey):
    return make_model("ensemble", {"members": MEMBERS}).fit(survey)


def test_vote_takes_the_most_answered_group_and_the_earliest_member_on_a_tie():
    answers = np.array([[0, 1, 1], [2, 0, 2], [3, 4, 5], [1, 2, 2], [7, 7, 7], [5, 6, 6]])
    assert vote_groups(answers).tolist() == [1, 2, 3, 2, 7, 6]
    assert vote_groups(np.array([[4, 9], [9, 4]])).tolist() == [4, 9]  # tie: the first member's


def _pred(xy, floor, building, cov):
    n = len(xy)
    xy = np.asarray(xy, dtype=float)
    return Prediction(x=xy[:, 0], y=xy[:, 1], floor=np.asarray(floor), building=np.asarray(building),
                      covariance=np.asarray(cov, dtype=float), best_rp=np.zeros(n, int),
                      top_rp=np.zeros((n, 1), int), top_p=np.ones((n, 1)))


@pytest.mark.parametrize("position", ["mean", "median"])
def test_the_members_on_the_voted_floor_give_the_position_and_covariance(model, survey, monkeypatch, position):
    m = EnsembleModel(members=MEMBERS, position=position).fit(survey)
    c0, c1, c2 = (np.diag([1.0, 2.0]), np.diag([3.0, 1.0]), np.diag([9.0, 9.0]))
    # one query: members 1 and 2 say floor 1, member 0 floor 0 (outvoted; its position must not count)
    preds = [_pred([[0.0, 0.0]], [0], [0], [c0]), _pred([[2.0, 4.0]], [1], [0], [c1]),
             _pred([[4.0, 8.0]], [1], [0], [c2])]
    monkeypatch.setattr(m, "_member_predictions", lambda *a, **k: preds)
    p = m.predict(np.full((1, len(m.tx_ids_)), np.nan))
    assert p.floor.tolist() == [1] and p.building.tolist() == [0]
    assert (p.x[0], p.y[0]) == pytest.approx((3.0, 6.0))  # mean = median of two
    d1, d2 = np.array([-1.0, -2.0]), np.array([1.0, 2.0])
    expected = (c1 + np.outer(d1, d1) + c2 + np.outer(d2, d2)) / 2
    np.testing.assert_allclose(p.covariance[0], expected)


def test_median_differs_from_mean_with_three_agreeing_members(survey, monkeypatch):
    c = np.eye(2)
    preds = [_pred([[0.0, 0.0]], [1], [0], [c]), _pred([[1.0, 1.0]], [1], [0], [c]),
             _pred([[11.0, 2.0]], [1], [0], [c])]
    for position, xy in (("mean", (4.0, 1.0)), ("median", (1.0, 1.0))):
        m = EnsembleModel(members=MEMBERS, position=position).fit(survey)
        monkeypatch.setattr(m, "_member_predictions", lambda *a, **k: preds)
        p = m.predict(np.full((1, len(m.tx_ids_)), np.nan))
        assert (p.x[0], p.y[0]) == pytest.approx(xy)


def test_real_members_combine_as_documented(model, survey, scans):
    p = model.predict(scans)
    # the members answer as the same models fitted alone
    alone = [make_model(s["algorithm"], s["params"]).fit(survey).predict(scans) for s in MEMBERS]
    G = np.column_stack([a.building * 100 + a.floor for a in alone])
    key = vote_groups(G)
    assert np.array_equal(p.floor, key % 100) and np.array_equal(p.building, key // 100)
    on = G == key[:, None]
    XY = np.stack([a.xy for a in alone], axis=1)  # (n, members, 2)
    expected = (XY * on[..., None]).sum(1) / on.sum(1)[:, None]
    np.testing.assert_allclose(p.xy, expected, atol=1e-9)
    assert (~on).any(), "the scans should make some members disagree on the floor"
    assert not np.allclose(p.xy, alone[0].xy)
    cands = model.locate_many(scans[:10])
    for fx in cands:
        probs = [c.probability for c in fx.candidates]
        assert probs == sorted(probs, reverse=True) and sum(probs) <= 1.0 + 1e-9
        assert all(c.floor == fx.floor for c in fx.candidates)


def test_locate_answers_a_fix_with_a_usable_covariance(model, scans):
    fx = model.locate(scans[0])
    cov = np.asarray(fx.covariance)
    assert cov.shape == (2, 2) and np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) >= model.cov_floor_m_**2 - 1e-9)
    assert fx.reference_point is not None and fx.candidates


def test_artifact_round_trip_answers_the_same(model, scans):
    blob = to_bytes(model)
    back = from_bytes(blob)
    assert isinstance(back, EnsembleModel) and back.get_params() == model.get_params()
    a, b = model.predict(scans), back.predict(scans)
    for f in ("x", "y", "floor", "building", "covariance", "best_rp", "top_rp", "top_p"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    fa, fb = model.locate(scans[5]), back.locate(scans[5])
    assert (fa.x, fa.y, fa.floor, fa.reference_point) == (fb.x, fb.y, fb.floor, fb.reference_point)


def test_training_step_reuses_member_choices_and_stores_no_validation_models(survey, scans):
    m, v = fit_and_validate(lambda: make_model("ensemble"), survey, how="points")
    assert [s["algorithm"] for s in m.members] == [s["algorithm"] for s in DEFAULT_MEMBERS]
    assert not hasattr(m, "_reused")
    assert m.members_[0].calibrate is None  # the wknn member took its validated k instead of choosing again
    assert np.isfinite(v.metrics.mean_error_m)
    back = from_bytes(to_bytes(m))
    np.testing.assert_array_equal(back.predict(scans).covariance, m.predict(scans).covariance)


@pytest.mark.parametrize("params", [
    {"members": [{"algorithm": "magic"}]},
    {"members": [{"algorithm": "wknn", "params": {"nope": 1}}]},
    {"members": [{"algorithm": "ensemble"}]},
    {"members": [{"algorithm": "knn", "params": {"kinds": ["wifi"]}}]},
    {"members": []},
    {"members": [{"algorithm": "knn", "extra": 1}]},
    {"position": "mode"},
    {"floor_classifier": "svc"},
])
def test_bad_parameters_are_refused_at_once(params):
    with pytest.raises(ValueError):
        make_model("ensemble", params)
