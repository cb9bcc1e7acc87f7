"""The particle filter's stored state: a byte per number (``tracking.packed``), held exactly by
the filter, and the older stored forms still load."""

import base64
import json
import math

import numpy as np
import pytest

from server.estimation.floorplan import Walkable
from server.estimation.tracking import make_tracker, packed, tracker_from_dict
from server.estimation.types import Fix, Step


def _through_json(t):
    return tracker_from_dict(json.loads(json.dumps(t.to_dict())))


def _assert_same(a, b):
    np.testing.assert_array_equal(a.particles, b.particles)
    np.testing.assert_array_equal(a.weights, b.weights)
    assert a.rng.bit_generator.state == b.rng.bit_generator.state


# -- the codes ---------------------------------------------------------------------------------
def test_grid_keeps_values_within_half_a_step_and_rounding_again_changes_nothing():
    rng = np.random.default_rng(0)
    a = np.column_stack([5000.0 + 3.0 * rng.standard_normal(500), rng.standard_normal(500),
                         np.full(500, 0.7)])  # the last column has no spread
    lo, step = packed.fit_grid(a)
    assert step[2] == 0.0
    r = packed.snap(a, lo, step)
    assert np.all(np.abs(r - a) <= 0.5 * step + 1e-9)
    np.testing.assert_array_equal(r[:, 2], 0.7)
    assert packed.on_grid(r, lo, step).all()
    assert not packed.on_grid(a, lo, step)[:2].any()
    np.testing.assert_array_equal(packed.snap(r, lo, step), r)
    np.testing.assert_array_equal(packed.unpack(json.loads(json.dumps(packed.pack_grid(r, lo, step)))), r)
    # values off the grid's ends are taken to them
    assert not packed.on_grid(r + 100.0, lo, step)[:2].any()
    np.testing.assert_array_equal(packed.snap(r + 1e4, lo, step)[:, 0], lo[0] + 255 * step[0])



@pytest.mark.parametrize("order", ["C", "F"])
def test_snap_gives_what_loading_the_codes_gives_in_either_layout(order):
    """The filter holds particles column-major; a snapped value must be bit for bit the value
    its stored code loads as, on and off the grid and in a column without spread."""
    rng = np.random.default_rng(1)
    a = np.column_stack([-40.0 + 7.0 * rng.standard_normal(300), 1e3 * rng.standard_normal(300),
                         np.full(300, -2.5)])
    lo, step = packed.fit_grid(a)
    for x in (a, a + 0.3 * step * rng.standard_normal(a.shape), a + 1e3):
        x = np.asarray(x, order=order)
        s = packed.snap(x, lo, step)
        assert s.flags.f_contiguous == (order == "F")
        np.testing.assert_array_equal(s, packed.unpack(packed.pack_grid(s, lo, step)))
        np.testing.assert_array_equal(s, np.clip(s, lo, lo + 255 * step))

def test_weight_ratios_are_the_nearest_doubles():
    r = packed._RATIO
    assert r[0] == 1.0 and r[16] == 0.5 and r[8] == math.sqrt(0.5) and r[255] == 0.0
    np.testing.assert_array_equal(r[16:255], r[:239] / 2)
    assert np.all(np.diff(r) < 0)


def test_weights_as_stored_are_within_their_tolerance_and_stable():
    rng = np.random.default_rng(1)
    w = np.exp(-0.5 * (4.0 * rng.standard_normal(1000)) ** 2)
    w /= w.sum()
    s = packed.weights_as_stored(w)
    assert s.sum() == pytest.approx(1.0, abs=1e-12)
    kept = w / w.max() > 2.0**-15.9
    ratio = (s / s.max())[kept] / (w / w.max())[kept]
    assert np.all(np.abs(np.log2(ratio)) <= 1 / 32 + 1e-12)  # ±2.2 % of the ratio to the largest
    assert np.all(s[~kept] == 0.0)
    np.testing.assert_array_equal(packed.weights_as_stored(s), s)
    data = json.loads(json.dumps(packed.pack_weights(s)))
    np.testing.assert_array_equal(packed.unpack_weights(data, 1000), s)
    uniform = packed.weights_as_stored(np.full(1000, 1e-3))
    np.testing.assert_array_equal(uniform, np.full(1000, 1.0 / 1000))
    assert packed.pack_weights(uniform) is None
    np.testing.assert_array_equal(packed.unpack_weights(None, 1000), uniform)


@pytest.mark.parametrize("n", [0, 1, 2, 3, 4, 5, 7, 8, 13, 1000, 4001])
def test_base85_is_the_standard_librarys(n):
    raw = np.random.default_rng(n).integers(0, 256, n).astype(np.uint8).tobytes()
    text = packed.b85encode(raw)
    assert text == base64.b85encode(raw).decode("ascii")
    assert packed.b85decode(text) == raw
    for cut in range(min(len(text), 12) + 1):  # what the standard library refuses, refused too
        try:
            expected = base64.b85decode(text[:cut])
        except ValueError:
            with pytest.raises(ValueError):
                packed.b85decode(text[:cut])
        else:
            assert packed.b85decode(text[:cut]) == expected


@pytest.mark.parametrize("text", ["~~~~~", "|NsC0~", 'ab"c', "{{{{{", "abcé"])
def test_base85_refuses_what_the_standard_library_refuses(text):
    try:
        expected = base64.b85decode(text)
    except ValueError:
        with pytest.raises(ValueError):
            packed.b85decode(text)
    else:
        assert packed.b85decode(text) == expected


def test_damaged_codes_are_refused():
    a = np.arange(8.0).reshape(4, 2)
    data = packed.pack_grid(a, *packed.fit_grid(a))
    with pytest.raises(ValueError):
        packed.unpack({**data, "shape": [5, 2]})
    with pytest.raises(ValueError):
        packed.unpack({**data, "u8": "not base85 ~~~~"})
    with pytest.raises(ValueError):
        packed.unpack_weights({"log2": packed._text(np.full(4, 255, np.uint8)), "per_octave": 16}, 4)
    with pytest.raises(ValueError):
        packed.unpack_weights({"log2": packed._text(np.zeros(4, np.uint8)), "per_octave": 8}, 4)


# -- the filter holds what it stores -------------------------------------------------------------
@pytest.mark.parametrize("name", ["pf", "pf-xy"])
def test_a_filter_restored_after_every_input_continues_exactly(name):
    """Steps into a dead end (wall kills, a redraw), fixes (reweighting, resampling), a range and
    an inflation: a filter that goes through JSON after every input ends bit for bit as one that
    never did."""
    area = Walkable([[[0, 0], [10, 0], [10, 2], [0, 2], [0, 0]]])
    walls = [[0.0, 2.0, 10.0, 2.0], [10.0, 0.0, 10.0, 2.0]]
    events = ([Step(k, 0.7, 90.0 + 10 * (-1) ** k) for k in range(8)]
              + [Fix(6.0, 1.0, 0, np.eye(2) * 0.5), Step(9, 10.0, 90.0, length_std_m=0.0, heading_std_deg=0.0),
                 Fix(8.5, 1.2, 0, np.diag([1.0, 0.3])), ("range", [9.0, 1.0], 1.0, 0.5), ("inflate", 2.0),
                 Step(10, 0.7, 270.0), Fix(8.0, 1.0, 0, np.eye(2) * 4.0)])
    kinds = set()

    def apply(t, e):
        t.set_walkable(area)
        if isinstance(e, Step):
            t.predict(e)
        elif isinstance(e, Fix):
            t.update(e)
        elif e[0] == "range":
            t.update_range(e[1], e[2], e[3])
        else:
            t.inflate(e[1])

    a = make_tracker(name, [2.0, 1.0], np.eye(2) * 0.2, walls=walls, seed=3)
    b = make_tracker(name, [2.0, 1.0], np.eye(2) * 0.2, walls=walls, seed=3)
    for e in events:
        apply(a, e)
        b = _through_json(b)
        apply(b, e)
        _assert_same(a, b)
        kinds.add(bool(np.all(a.weights == a.weights[0])))
        if isinstance(e, Step) and e.length_m == 10.0:  # every particle would leave: redrawn inside
            assert area.contains(a.particles[:, :2]).all()
        np.testing.assert_array_equal(_through_json(a).particles, a.particles)
        assert a._grid is not None and packed.on_grid(a.particles, *a._grid).all()  # as stored, not rounded again
    assert kinds == {True, False}  # stored with uniform and with other weights


def test_a_redraw_keeps_the_draws_as_judged():
    area = Walkable([[[0, 0], [10, 0], [10, 2], [0, 2], [0, 0]]])
    t = make_tracker("pf", [9.5, 1.0], np.eye(2) * 0.01, seed=5, q=0.0)
    t.set_walkable(area)
    t.predict(Step(0, 2.0, 90.0, length_std_m=0.0, heading_std_deg=0.0))  # beyond x = 10: a redraw
    assert area.contains(t.particles[:, :2]).all()
    assert t._grid is not None and packed.on_grid(t.particles, *t._grid).all()
    _assert_same(_through_json(t), t)


def test_stored_state_of_a_thousand_particles_is_small():
    t = make_tracker("pf", [3.0, 4.0], np.eye(2) * 4.0, seed=5)
    t.predict(Step(1.0, 0.7, 45.0))
    state = t.to_dict()["state"]
    assert state["weights"] is None
    assert len(json.dumps(state["particles"])) < 5300  # 4,000 codes: ≤ 5,000 characters and the grid
    t.update(Fix(3.5, 4.5, 0, np.eye(2) * 3.0))
    state = t.to_dict()["state"]
    assert state["weights"] is not None and len(json.dumps(state["weights"])) < 1300
    assert len(json.dumps(state)) < 7000  # as float16 offsets and float32 weights: 16,400


def test_non_finite_particles_are_kept_as_float32():
    """No grid holds them (such a filter is lost anyway: its mean is not finite): stored as
    float32, as before the grid, rather than failing."""
    t = make_tracker("pf-xy", [0.0, 0.0], np.eye(2), seed=2)
    t.particles[3, 0] = np.inf
    t._quantize()
    assert t._grid is None
    with np.errstate(invalid="ignore"):
        stored = t._state()["particles"]
    assert "f4" in stored
    np.testing.assert_array_equal(packed.unpack(stored), t.particles)
    np.testing.assert_array_equal(t.particles, t.particles.astype(np.float32))


# -- older stored forms ----------------------------------------------------------------------------
def _b64(a, dtype):
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _f2(p):  # float16 offsets from their mean, float64 in the JSON (stored before the grid)
    anchor = p.mean(axis=0)
    return {"f2": _b64(p - anchor, "<f2"), "shape": list(p.shape), "anchor": anchor.tolist()}


def _f4(a):
    return {"f4": _b64(a, "<f4"), "shape": list(a.shape)}


OLD_FORMS = {
    "f2 offsets, f4 weights": (lambda p: _f2(p), lambda w: _f4(w)),
    "f2 offsets, uniform": (lambda p: _f2(p), lambda w: None),
    "f4 values, f4 weights": (lambda p: _f4(p), lambda w: _f4(w)),
    "lists": (lambda p: p.tolist(), lambda w: w.tolist()),
}


@pytest.mark.parametrize("form", sorted(OLD_FORMS))
@pytest.mark.parametrize("name", ["pf", "pf-xy"])
def test_older_stored_forms_load(name, form):
    """Each older form loads as its values on a grid (positions within half a step: the cloud's
    spread / 510) and its weights within 2.2 %; from then on the filter stores what it holds."""
    t = make_tracker(name, [30.0, -12.0], np.eye(2) * 2.0, seed=4)
    t.predict(Step(0, 0.7, 10.0))
    t.update(Fix(30.5, -11.0, 0, np.eye(2) * 3.0))
    p = t.particles + 1e-4 * np.random.default_rng(0).standard_normal(t.particles.shape)  # off the grid
    w = t.weights if OLD_FORMS[form][1](t.weights) is not None else np.full(len(p), 1.0 / len(p))
    data = json.loads(json.dumps(t.to_dict()))
    pack_p, pack_w = OLD_FORMS[form]
    data["state"]["particles"] = pack_p(p)
    data["state"]["weights"] = pack_w(w)
    old = packed.unpack(data["state"]["particles"]).reshape(p.shape)
    back = tracker_from_dict(json.loads(json.dumps(data)))
    assert back._grid is not None
    assert np.all(np.abs(back.particles - old) <= 0.5 * back._grid[1] + 1e-12)
    np.testing.assert_allclose(back.weights, w, rtol=0.045)
    np.testing.assert_allclose(back.mean, w @ old[:, :2], atol=0.01)
    again = _through_json(back)
    _assert_same(again, back)
    for tr in (back, again):
        tr.predict(Step(1, 0.7, 10.0))
    _assert_same(again, back)
