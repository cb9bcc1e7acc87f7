"""The hierarchical weighted KNN (wknn): building hierarchy, device-offset robustness,
calibrated covariance, speed-path consistency, and artifact safety."""

import hashlib
import io
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from server.estimation.fingerprint import (
    ArtifactError,
    FingerprintSet,
    WKNNModel,
    checksum,
    from_bytes,
    make_model,
    to_bytes,
)
from server.estimation.fingerprint.artifact import LIBRARY_VERSION, MAGIC
from server.estimation.fingerprint.calibration import IDENTITY
from tests.helpers.synthetic import make_site, with_prefix


@pytest.fixture(scope="module")
def campus():
    """Two buildings 60 m apart, both with floors 0 and 1 and their own transmitters;
    building 1's scans also hear one of building 0's access points, weakly."""
    b0 = with_prefix(make_site(seed=11, noise_db=2.0), "b0")
    b1 = with_prefix(make_site(seed=12, noise_db=2.0), "b1")
    shared = dict(b0.transmitters[0])
    rows = []
    for b, site in ((0, b0), (1, b1)):
        fs = site.survey(scans_per_rp=4, seed=3 + b)
        for r in fs.to_rows():
            r["building"] = b
            r["label"] = f"b{b}-{r['label']}"
            r["x"] += 60.0 * b
            if b == 1:
                r["rss"][shared["id"]] = -95.0
            rows.append(r)
    return b0, b1, FingerprintSet.from_rows(rows)


def test_a_scan_in_building_1_never_answers_building_0(campus):
    b0, b1, fs = campus
    model = make_model("wknn").fit(fs)
    rng = np.random.default_rng(0)
    scans, truth_floor = [], []
    for _, x, y, f in b1.rp:
        for _ in range(3):
            s = b1.scan(x, y, f, None, rng, noise_db=4.0)
            s[b0.transmitters[0]["id"]] = -70.0  # building 0's AP heard strongly through a window
            scans.append(s)
            truth_floor.append(f)
    pred = model.predict(scans)
    assert np.all(pred.building == 1)
    fixes = model.locate_many(scans)
    assert all(fx.reference_point.startswith("b1-") for fx in fixes)
    assert all(c.label.startswith("b1-") for fx in fixes for c in fx.candidates)
    assert np.mean(pred.floor == np.array(truth_floor)) >= 0.95
    assert np.all(pred.x > 50.0)  # positions inside building 1 (x offset by 60 m)


@pytest.fixture(scope="module")
def site_and_model():
    site = make_site(nx=7, ny=5, seed=4, noise_db=2.0)
    fs = site.survey(scans_per_rp=6, seed=1)
    return site, make_model("wknn").fit(fs)


@pytest.mark.parametrize("shift_db", [8.0, -8.0])
def test_a_shifted_scan_answers_close_to_the_unshifted_one(site_and_model, shift_db):
    site, model = site_and_model
    rng = np.random.default_rng(2)
    scans, truth = [], []
    for _, x, y, f in site.rp:
        scans.append(site.scan(x, y, f, None, rng))
        truth.append((x, y, f))
    shifted = [{t: v + shift_db for t, v in s.items()} for s in scans]
    a, b = model.predict(scans), model.predict(shifted)
    t = np.array(truth)
    err_a = np.hypot(a.x - t[:, 0], a.y - t[:, 1])
    err_b = np.hypot(b.x - t[:, 0], b.y - t[:, 1])
    moved = np.hypot(a.x - b.x, a.y - b.y)
    assert np.mean(b.floor == t[:, 2]) >= 0.95
    assert err_b.mean() <= err_a.mean() + 2.5, (err_a.mean(), err_b.mean())
    assert np.median(moved) <= 2.5
    # without the per-query offset estimate the shift hurts clearly more
    plain = make_model("wknn", {"offset_estimate": False, "k": model.k_}).fit(model_training_set(site))
    c = plain.predict(shifted)
    err_c = np.hypot(c.x - t[:, 0], c.y - t[:, 1])
    assert err_b.mean() <= 0.75 * err_c.mean(), (err_b.mean(), err_c.mean())


def test_the_offset_is_estimated_only_from_enough_shared_transmitters(site_and_model):
    """With fewer than ``offset_min_tx`` transmitters heard both by a scan and its nearest
    fingerprints an offset cannot be told from a place, and none is estimated."""
    site, model = site_and_model
    _, x, y, f = site.rp[len(site.rp) // 2]
    scan = {t: v + 6.0 for t, v in site.scan(x, y, f, None, np.random.default_rng(5)).items()}
    few = dict(sorted(scan.items(), key=lambda kv: -kv[1])[: model.offset_min_tx - 1])

    def offset(m, s):
        q = m.encoder_.transform(m.scan_matrix([s]))[0]
        return m._estimate_offset(q, *m._query_distances(q, None))

    assert len(scan) >= model.offset_min_tx == 8
    assert offset(model, scan) < -0.5  # (a first estimate: the iterations take it further)
    assert offset(model, few) == 0.0
    every = make_model("wknn", {"offset_min_tx": 1, "k": model.k_}).fit(model_training_set(site))
    assert offset(every, few) < -0.5


def model_training_set(site):
    return site.survey(scans_per_rp=6, seed=1)


def test_covariance_is_calibrated_on_held_out_reference_points():
    """Survey three quarters of the grid, query the rest: the normalised innovation
    squared rᵀC⁻¹r of the fixes averages near 2 (a calibrated 2-D Gaussian)."""
    site = make_site(nx=7, ny=5, seed=2, noise_db=2.0)
    full = site.survey(scans_per_rp=6, seed=2)
    held = {lab for k, (lab, _, _, _) in enumerate(site.rp) if k % 4 == 0}
    train = full.subset(np.array([lab not in held for lab in full.label]))
    rng = np.random.default_rng(3)
    scans, truth = [], []
    for lab, x, y, f in site.rp:
        if lab in held:
            for _ in range(5):
                scans.append(site.scan(x, y, f, None, rng))
                truth.append((x, y))
    t = np.array(truth)

    def mean_nis(model):
        pred = model.predict(scans)
        r = pred.xy - t
        return float(np.mean(np.einsum("ni,nij,nj->n", r, np.linalg.inv(pred.covariance), r)))

    calibrated = make_model("wknn").fit(train)
    raw = make_model("wknn", {"calibrate": None}).fit(train)
    nis = mean_nis(calibrated)
    assert 1.0 <= nis <= 3.0, nis
    assert calibrated.calibration_ != IDENTITY and raw.calibration_ == IDENTITY
    assert mean_nis(raw) != nis


def test_k_is_chosen_by_cross_validation_and_a_given_k_is_kept(site_and_model):
    site, model = site_and_model
    assert model.k_ in model.k_grid and len(model.k_cv_errors_) == len(model.k_grid)
    fixed = make_model("wknn", {"k": 2, "calibrate": None}).fit(model_training_set(site))
    assert fixed.k_ == 2


def test_duplicates_and_rare_transmitters_are_cleaned(site_and_model):
    site, _ = site_and_model
    fs = site.survey(scans_per_rp=3, seed=5)
    twice = FingerprintSet.from_rows(fs.to_rows() + fs.to_rows()[:10] + [
        {"x": 0.0, "y": 0.0, "floor": 0, "label": site.rp[0][0], "rss": {"wifi:lonely": -50.0, **fs.scans()[0]}}])
    model = make_model("wknn", {"k": 3, "calibrate": None}).fit(twice)
    assert model.XT_.shape[1] == len(fs) + 1  # the 10 duplicates dropped, the new row kept
    lonely = model.tx_ids_.index("wifi:lonely")
    assert not model.tx_active_[lonely]


def test_one_query_and_a_batch_agree(site_and_model):
    site, model = site_and_model
    scans = site.survey(scans_per_rp=1, seed=9).scans()[:12]
    batch = model.locate_many(scans)
    for s, fb in zip(scans, batch, strict=True):
        fx = model.locate(s)
        assert (fx.x, fx.y, fx.floor) == pytest.approx((fb.x, fb.y, fb.floor))


# ---- artifacts: no code runs when loading ------------------------------------------------
def _blob_with(payload: bytes) -> bytes:
    return MAGIC + hashlib.sha256(payload).digest() + payload


def _npz(doc: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, __doc__=np.frombuffer(json.dumps(doc).encode(), dtype=np.uint8))
    return buf.getvalue()


class _Boom:
    def __reduce__(self):
        return (pytest.fail, ("unpickling ran code",))


def test_a_pickled_artifact_is_refused_without_being_run():
    payload = pickle.dumps(_Boom())
    for blob in (b"LOCFP1\n" + hashlib.sha256(payload).digest() + payload, _blob_with(payload)):
        with pytest.raises(ArtifactError):
            from_bytes(blob)
    old = b"LOCFP1\n" + hashlib.sha256(payload).digest() + payload
    with pytest.raises(ArtifactError, match="retrain"):
        from_bytes(old)
    with pytest.raises(ArtifactError, match="retrain"):
        checksum(old)  # the server checks the recorded hash first


def test_a_tampered_artifact_naming_another_class_is_refused():
    doc = {"library_version": LIBRARY_VERSION,
           "model": {"$o": "os:system", "state": {"cmd": "echo pwned"}}}
    with pytest.raises(ArtifactError, match="may not be loaded"):
        from_bytes(_blob_with(_npz(doc)))
    doc["model"] = {"$o": "subprocess:Popen", "state": {}}
    with pytest.raises(ArtifactError, match="may not be loaded"):
        from_bytes(_blob_with(_npz(doc)))


def test_an_npz_with_an_object_array_is_refused():
    buf = io.BytesIO()
    np.savez(buf, __doc__=np.array([_Boom()], dtype=object))
    with pytest.raises(ArtifactError):
        from_bytes(_blob_with(buf.getvalue()))


def test_an_artifact_of_another_library_version_is_refused(site_and_model):
    _, model = site_and_model
    blob = to_bytes(model)
    assert isinstance(from_bytes(blob), type(model))
    doc = {"library_version": "fingerprint-0.1", "model": None}
    with pytest.raises(ArtifactError, match="retrain"):
        from_bytes(_blob_with(_npz(doc)))


@pytest.mark.parametrize("candidates", [12, 40, 96])
def test_the_fast_hierarchy_equals_the_full_one(campus, candidates):
    b0, b1, fs = campus
    model = make_model("wknn", {"k": 4, "calibrate": None}).fit(fs)
    model.CANDIDATES = candidates  # few candidates: many queries take the fallback
    rng = np.random.default_rng(1)
    scans = [site.scan(x, y, f, None, rng, noise_db=5.0) for site in (b0, b1) for _, x, y, f in site.rp]
    Q = model.encoder_.transform(model.scan_matrix(scans))
    D = model._distances(Q, None)
    assert np.allclose(model._hierarchy_scores(D), model._scores(model._restrict(D), model.k_))


def test_a_scan_resembling_nothing_surveyed_is_out_of_coverage(site_and_model):
    site, model = site_and_model
    rng = np.random.default_rng(4)
    inside = [site.scan(x, y, f, None, rng) for _, x, y, f in site.rp]
    _, ok = model.coverage(inside)
    assert ok.mean() >= 0.9
    ids = [t["id"] for t in site.transmitters]
    strange = [{ids[j]: float(rng.uniform(-95, -30)) for j in rng.choice(len(ids), 3, replace=False)}
               for _ in range(20)]  # 3 transmitters, random levels: no surveyed place looks like that
    far, ok = model.coverage(strange)
    assert ok.mean() <= 0.3 and np.all(np.isfinite(far))


def test_the_reduction_over_weighted_points_equals_the_dense_one(campus):
    from server.estimation.fingerprint.base import FingerprintModel

    b0, b1, fs = campus
    model = make_model("wknn", {"k": 5}).fit(fs)
    rng = np.random.default_rng(6)
    scans = [site.scan(x, y, f, None, rng, noise_db=4.0) for site in (b0, b1) for _, x, y, f in site.rp]
    Q = model.encoder_.transform(model.scan_matrix(scans))
    logs = model._log_scores(Q, None, None)
    fast = model._reduce(logs)
    dense = FingerprintModel._reduce(model, logs)
    assert np.allclose(fast.xy, dense.xy) and np.array_equal(fast.floor, dense.floor)
    assert np.array_equal(fast.building, dense.building) and np.array_equal(fast.best_rp, dense.best_rp)
    assert np.allclose(fast.covariance, dense.covariance)  # both raw: predict calibrates
    live = dense.top_p > 0
    assert np.array_equal(np.where(live, fast.top_rp, -1), np.where(live, dense.top_rp, -1))
    assert fast.top_rp.shape == (len(scans), model.n_candidates)


# ---- the fast query path answers what the full computation answered --------------------------
REFERENCE = Path(__file__).with_name("wknn_reference.json")


def _reference_case():
    """A two-building campus whose far transmitters go unheard (a scan's candidates are a
    subset of the fingerprints), the model fitted on it, and its queries: noisy scans at
    every reference point, some shifted by ±8 dB, scans hearing one or two transmitters,
    and (x, y, floor, radius) restrictions for a third of them."""
    sites = [with_prefix(make_site(nx=8, ny=5, spacing_m=4.0, n_wifi=10, n_ble=6, seed=21 + b, noise_db=2.0,
                               sensitivity_dbm=-80.0), f"b{b}") for b in (0, 1)]
    rows = []
    for b, site in enumerate(sites):
        for r in site.survey(scans_per_rp=3, seed=7 + b).to_rows():
            rows.append({**r, "building": b, "label": f"b{b}-{r['label']}", "x": r["x"] + 40.0 * b})
    # the offset estimated from every scan, as when the reference was made (offset_min_tx came later)
    model = make_model("wknn", {"offset_min_tx": 1}).fit(FingerprintSet.from_rows(rows))
    rng = np.random.default_rng(8)
    scans, near = [], []
    for b, site in enumerate(sites):
        for i, (_, x, y, f) in enumerate(site.rp):
            s = site.scan(x, y, f, None, rng, noise_db=4.0)
            if i % 5 == 1:
                s = {t: v + (8.0 if b else -8.0) for t, v in s.items()}
            if i % 13 == 2:
                s = dict(list(s.items())[: 1 + i % 2])
            scans.append(s)
            near.append((x + 40.0 * b + 3.0, y, f, 6.0) if i % 3 == 0 else None)
    return model, scans, near


def _reference_answers(model, scans, near) -> dict:
    """Raw (uncalibrated) answers one scan at a time, as ``locate`` asks, and the coverage distances."""
    out: dict = {"k": model.k_, "x": [], "y": [], "floor": [], "building": [], "covariance": [], "best_rp": []}
    for s, n in zip(scans, near, strict=True):
        pred = model.predict([s], near=None if n is None else n[:3], radius_m=None if n is None else n[3],
                             calibrated=False)
        for key in ("x", "y", "floor", "building", "best_rp"):
            out[key].append(getattr(pred, key)[0].item())
        out["covariance"].append(pred.covariance[0].ravel().tolist())
    out["nearest"] = model.coverage(scans)[0].tolist()
    return out


@pytest.fixture(scope="module")
def reference_case():
    return _reference_case()


def test_the_fast_path_answers_as_the_full_computation_did(reference_case):
    """Against answers the full computation (before the candidate-subset path, commit
    6c0b060) gave on this campus; regenerate with
    ``python -m tests.estimation.test_fingerprint_wknn`` on that commit."""
    expected = json.loads(REFERENCE.read_text())
    model, scans, near = reference_case
    assert model.k_ == expected["k"]
    for candidates in (8, 30, 96):  # few: many queries take the full-row fallback
        model.CANDIDATES = candidates
        got = _reference_answers(model, scans, near)
        model.CANDIDATES = WKNNModel.CANDIDATES
        for key in ("floor", "building", "best_rp"):
            assert got[key] == expected[key], (candidates, key)
        for key in ("x", "y", "covariance", "nearest"):
            assert np.allclose(got[key], expected[key], rtol=1e-6, atol=1e-6), (candidates, key)



def test_candidate_distances_are_the_full_rows_distances(reference_case):
    """A query's candidates carry the full row's distances bit for bit; every other fingerprint is at exactly 1."""
    model, scans, _ = reference_case
    Q = model.encoder_.transform(model.scan_matrix(scans))
    F = model.XT_.T.astype(np.float64)
    for q in Q:
        cand, d = model._query_distances(q, None)
        qq = q.astype(np.float64) * model.tx_active_
        dense = np.abs(F - qq).sum(axis=1) / (F.sum(axis=1) + qq.sum())
        assert len(cand) < len(F) and np.allclose(d, dense[cand], rtol=1e-6)
        assert np.all(dense[np.setdiff1d(np.arange(len(F)), cand)] == pytest.approx(1.0))
        assert np.array_equal(model._full_row(cand, d), model._distances(q[None], None)[0])


def test_locate_covered_is_locate_and_coverage_from_one_pass(site_and_model):
    site, model = site_and_model
    rng = np.random.default_rng(7)
    scans = [site.scan(x, y, f, None, rng) for _, x, y, f in site.rp[::4]]
    scans.append({t: v + 8.0 for t, v in scans[0].items()})
    for s in scans:
        fix, nearest = model.locate_covered(s)
        alone = model.locate(s)
        assert (fix.x, fix.y, fix.floor) == (alone.x, alone.y, alone.floor)
        assert np.array_equal(fix.covariance, alone.covariance)
        assert nearest == model.coverage([s])[0][0]
    shifted = [{t: v + 8.0 for t, v in s.items()} for s in scans]
    assert model.coverage(shifted)[1].mean() >= 0.9  # offset-corrected on both sides: a phone's offset is no strangeness


if __name__ == "__main__":
    REFERENCE.write_text(json.dumps(_reference_answers(*_reference_case())) + "\n")
