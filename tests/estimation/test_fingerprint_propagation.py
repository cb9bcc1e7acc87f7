"""Path-loss fit, multilateration, transmitter-only sites, cold-start fusion."""

import math

import numpy as np
import pytest

from server.estimation.fingerprint import PropagationModel, cold_start_fix, exp_weights, fuse_fixes
from server.estimation.radio import fit_path_loss, multilaterate, weighted_centroid
from server.estimation.types import Fix
from tests.helpers.synthetic import make_site


def test_fit_path_loss_recovers_r0_and_gamma():
    rng = np.random.default_rng(0)
    d = rng.uniform(1, 30, 400)
    rss = -42.0 - 10 * 2.7 * np.log10(d)
    assert fit_path_loss(d, rss) == pytest.approx((-42.0, 2.7), abs=1e-9)
    r0, g = fit_path_loss(d, rss + rng.normal(0, 3, d.size))
    assert abs(r0 + 42.0) < 1.5 and abs(g - 2.7) < 0.15
    with pytest.raises(ValueError):
        fit_path_loss([5.0, 5.0], [-60, -61])


def test_model_fits_radio_parameters_from_survey():
    site = make_site(seed=2, noise_db=1.0, floors=(0,), nx=8, ny=6, spacing_m=2.0)
    fs = site.survey(scans_per_rp=3, seed=0, headings=())
    positions_only = [{k: t[k] for k in ("id", "kind", "floor", "x", "y")} for t in site.transmitters]
    m = PropagationModel(transmitters=positions_only).fit(fs)
    by_id = {p["id"]: p for p in m.transmitter_params()}
    for t in site.transmitters:
        p = by_id[t["id"]]
        assert abs(p["tx_power_dbm"] - t["tx_power_dbm"]) < 2.5, t["id"]
        assert abs(p["path_loss_exponent"] - t["path_loss_exponent"]) < 0.3, t["id"]


def test_transmitter_positions_estimated_when_unknown():
    site = make_site(seed=2, noise_db=1.0, floors=(0,), nx=8, ny=6, spacing_m=2.0)
    fs = site.survey(scans_per_rp=3, seed=0, headings=())
    m = PropagationModel().fit(fs)  # no transmitter records at all
    assert all(p["x"] is not None for p in m.transmitter_params())
    fix = m.locate(site.scan(7.0, 5.0, 0, None, np.random.default_rng(1), noise_db=0.5))
    assert np.hypot(fix.x - 7.0, fix.y - 5.0) < 5.0


def test_site_with_transmitters_and_no_fingerprints():
    site = make_site(seed=4, floors=(0, 1), floor_loss_db=0.0)
    m = PropagationModel(transmitters=site.transmitters).fit(None)
    assert m.n_fingerprints_ == 0
    rng = np.random.default_rng(2)
    errs = []
    for x, y, f in ((3, 3, 0), (9, 6, 0), (6, 3, 1)):
        fix = m.locate(site.scan(x, y, f, None, rng, noise_db=0.0))
        errs.append(np.hypot(fix.x - x, fix.y - y))
        assert fix.candidates == [] and fix.reference_point is None
        assert np.all(np.linalg.eigvalsh(fix.covariance) > 0)
    assert np.mean(errs) < 2.0
    cen = PropagationModel(transmitters=site.transmitters, method="centroid").fit()
    assert np.isfinite(cen.locate(site.scan(6, 4, 0, None, rng, noise_db=0.0)).x)


def test_multilateration_exact_and_centroid_weights():
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    p = np.array([3.0, 4.0])
    ranges = np.hypot(*(anchors - p).T)
    xy, cov = multilaterate(anchors, ranges)
    assert np.allclose(xy, p, atol=1e-4)
    assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) > 0)
    c = weighted_centroid(anchors[:2], np.array([1.0, 3.0]))  # weights 1/d: 3:1
    assert np.allclose(c, [2.5, 0.0])


@pytest.mark.parametrize("off", [(1.0, 1.0, 1.0, 1.0), (1.1, 0.9, 1.05, 1.0)])
def test_multilateration_on_the_anchors_line_is_unsure_only_across_it(off):
    """Anchors in a line and the walker on it: the ranges fix the position along the line, not the side
    of it. The plain inverse of JᵀJ was singular there, and the fallback claimed σ ≈ 1 m every way."""
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    ranges = np.hypot(*(anchors - [12.0, 0.0]).T) * np.array(off)
    xy, cov = multilaterate(anchors, ranges)
    w, v = np.linalg.eigh(cov)
    assert np.all(np.isfinite(cov)) and w[0] > 0
    assert abs(v[0, 0]) == pytest.approx(1.0, abs=1e-6)  # the sure direction is along the line
    assert w[0] < 1.0 and w[1] > 100.0**2


def _fix(x, y, var, floor=0):
    return Fix(x=x, y=y, floor=floor, covariance=np.eye(2) * var)


def test_cold_start_weights_are_exp_minus_d_normalised():
    w = exp_weights([0.0, math.log(3.0)])
    assert np.allclose(w, [0.75, 0.25])
    a, b = _fix(0.0, 0.0, 1.0), _fix(4.0, 0.0, 1.0)
    fused = cold_start_fix(a, b, d_fingerprint=0.0, d_multilateration=math.log(3.0))
    assert fused.x == pytest.approx(1.0) and fused.y == pytest.approx(0.0)
    # mixture covariance: within + between (0.75·0.25·4² on x)
    assert fused.covariance[0, 0] == pytest.approx(1.0 + 0.75 * 0.25 * 16)
    assert fused.covariance[1, 1] == pytest.approx(1.0)
    # default d = RMS spread: the tighter estimate dominates
    tight, loose = _fix(0.0, 0.0, 1.0), _fix(10.0, 0.0, 9.0)
    f2 = cold_start_fix(tight, loose)
    assert f2.x == pytest.approx(10.0 * math.exp(-3) / (math.exp(-1) + math.exp(-3)))
    assert fuse_fixes([tight, loose]).x == pytest.approx(f2.x)


def test_cold_start_keeps_one_floor():
    fp, ml = _fix(0, 0, 1, floor=2), _fix(5, 5, 0.1, floor=1)
    assert cold_start_fix(fp, ml) is fp
    assert cold_start_fix(None, ml) is ml
    with pytest.raises(ValueError):
        cold_start_fix(None, None)
