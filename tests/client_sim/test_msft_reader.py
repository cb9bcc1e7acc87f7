"""The Microsoft walk-file reader and the PDR calibration helpers, on made-up data.

``tests/fixtures/msft_synthetic_walk.txt`` is a synthetic 6-s walk in the data set's
line format (not copied from it): 3 waypoints, 25 Hz IMU, three WiFi scan results
with stale, repeated and duplicated entries, iBeacons with and without a usable
major/minor, and lines of types the reader must skip (one truncated).
"""

from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from client_sim.batches import make_batches
from client_sim.errors import CliError
from client_sim.imu import ImuData
from client_sim.msft import (
    UncalibratedSteps,
    beacon_scans,
    calibration_window,
    dead_reckon,
    errors_against,
    fit_rotation_scale,
    interpolate_waypoints,
    read_walk,
    segment_displacements,
    steps_from_events,
    summarise,
    survey_rows,
    wifi_scans,
)
from client_sim.msft_eval import Prepared, default_split, select_walks, site_calibration
from client_sim.pdr.heading import GyroMagKalman, is_still

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "msft_synthetic_walk.txt"
T0 = 1700000000.0


@pytest.fixture(scope="module")
def walk():
    return read_walk(FIXTURE)


def test_parser_reads_sensors_waypoints_and_radio(walk):
    assert walk.name == "msft_synthetic_walk"
    assert walk.acc.shape == (150, 4) and walk.gyro.shape == (150, 4) and walk.mag.shape == (150, 4)
    assert walk.rotvec.shape == (150, 4)
    assert walk.acc[0, 0] == pytest.approx(T0) and walk.acc[1, 0] - walk.acc[0, 0] == pytest.approx(0.04)
    np.testing.assert_allclose(walk.waypoints, [[T0, 10, 20], [T0 + 4, 10, 24], [T0 + 6, 12, 24]])
    assert walk.t_start == pytest.approx(T0) and walk.t_end == pytest.approx(T0 + 6)
    assert len(walk.wifi) == 8  # the truncated TYPE_WIFI line is skipped
    assert {r.bssid for r in walk.wifi} == {f"aa:bb:cc:00:00:0{i}" for i in (1, 2, 3, 4)}  # lower-cased
    assert len(walk.beacons) == 4
    imu = walk.imu()
    assert imu.acc.shape == (150, 3) and imu.gyro.shape == (150, 3)


def test_beacon_ids_follow_the_api_and_split_placeholder_uuids_by_mac(walk):
    ids = [b.tx_id for b in walk.beacons]
    assert ids[0] == "ble:0a1b2c3d-0000-4000-8000-00000000abcd:7:42"
    assert "ble:deadbeef0002" in ids and "ble:deadbeef0003" in ids  # major = minor = 0: by mac


def test_waypoint_interpolation(walk):
    np.testing.assert_allclose(walk.truth_at(T0 + 2), [10, 22])
    np.testing.assert_allclose(walk.truth_at(T0 + 5), [11, 24])
    np.testing.assert_allclose(walk.truth_at([T0 - 1, T0 + 9]), [[10, 20], [12, 24]])  # clamped
    wp = np.array([[0.0, 0, 0], [10.0, 10, 0], [20.0, 10, 10]])
    np.testing.assert_allclose(interpolate_waypoints(wp, 15.0), [10, 5])


def test_wifi_scans_drop_stale_repeated_and_duplicate_entries(walk):
    scans = wifi_scans(walk, max_age_s=3.0)
    assert len(scans) == 2  # the third result only repeats an observation already reported
    first, second = scans
    # b was last seen 5 s before the scan: stale; c is listed twice: the newer reading wins
    assert first["rss"] == {"wifi:aa:bb:cc:00:00:01": -50.0, "wifi:aa:bb:cc:00:00:03": -65.0}
    assert first["t"] == pytest.approx(T0 + 1.3)  # median last-seen of the kept entries
    # a repeats its 1.4-s observation: not heard again; b is fresh; d has an empty ssid
    assert second["rss"] == {"wifi:aa:bb:cc:00:00:02": -58.0, "wifi:aa:bb:cc:00:00:04": -80.0}
    assert second["t"] == pytest.approx(T0 + 3.35)
    # a generous age keeps b in the first scan
    assert "wifi:aa:bb:cc:00:00:02" in wifi_scans(walk, max_age_s=10.0)[0]["rss"]


def test_beacon_windows(walk):
    scans = beacon_scans(walk, window_s=1.0)
    assert len(scans) == 2
    assert scans[0]["rss"] == {"ble:0a1b2c3d-0000-4000-8000-00000000abcd:7:42": -70.0, "ble:deadbeef0002": -88.0}
    assert scans[1]["rss"] == {"ble:deadbeef0003": -90.0}


def test_survey_rows_place_scans_on_the_waypoint_path(walk):
    rows = survey_rows(walk, wifi_scans(walk), device="d")
    assert [(r["x"], r["y"]) for r in rows] == [(10.0, 21.3), (10.0, 23.35)]
    assert rows[0]["floor"] == 0 and rows[0]["device"] == "d"
    out = survey_rows(walk, [{"t": T0 + 7, "rss": {"wifi:aa:bb:cc:00:00:01": -50.0}}])
    assert out == []  # outside the waypoint span: no truth, no fingerprint


def _events_along(waypoints: np.ndarray, offset_deg: float, k: float, per_s: float = 2.0) -> UncalibratedSteps:
    """Steps along the waypoint path whose magnetic heading is the truth minus
    ``offset_deg`` and whose Weinberg swing gives the true length with ``k``."""
    ts, swings, heads = [], [], []
    for (t0, x0, y0), (t1, x1, y1) in pairwise(waypoints):
        n = int(round((t1 - t0) * per_s))
        length = math.hypot(x1 - x0, y1 - y0) / n
        h = math.degrees(math.atan2(x1 - x0, y1 - y0))
        for i in range(n):
            ts.append(t0 + (i + 1) * (t1 - t0) / n)
            swings.append((length / k) ** 4)
            heads.append((h - offset_deg) % 360)
    return UncalibratedSteps(np.array(ts), np.array(swings), np.array(heads))


WAYPOINTS = np.array([[0.0, 0, 0], [10.0, 0, 12], [16.0, 7, 12], [26.0, 7, 0], [30.0, 12, 0]])


@pytest.mark.parametrize("offset,k", [(0.0, 0.45), (17.0, 0.4), (-25.0, 0.5), (183.0, 0.38)])
def test_heading_offset_and_step_scale_are_recovered(offset, k):
    ev = _events_along(WAYPOINTS, offset, k)
    pdr, true = segment_displacements(ev, WAYPOINTS, 1.0)
    off, scale = fit_rotation_scale(pdr, true)
    assert (off - offset + 180) % 360 - 180 == pytest.approx(0, abs=1e-6)
    assert scale == pytest.approx(k, rel=1e-6)
    # only the first segment: the same answer (no noise here), and it stops in time
    t_cal = calibration_window(WAYPOINTS, min_distance_m=10.0)
    assert t_cal == 10.0
    p1, t1 = segment_displacements(ev, WAYPOINTS, 1.0, t_until=t_cal)
    assert len(p1) == 1
    assert fit_rotation_scale(p1, t1)[1] == pytest.approx(k, rel=1e-6)
    # corrected steps dead-reckon onto the waypoints
    steps = steps_from_events(ev, scale, off)
    track = dead_reckon(steps, WAYPOINTS[0, 1:], 0.0)
    np.testing.assert_allclose(track[-1, 1:], WAYPOINTS[-1, 1:], atol=1e-6)


def test_heading_offset_with_noise_is_close():
    rng = np.random.default_rng(0)
    ev = _events_along(WAYPOINTS, 12.0, 0.42)
    noisy = UncalibratedSteps(ev.t, ev.swing * rng.uniform(0.8, 1.2, len(ev.t)),
                       ev.heading_deg + rng.normal(0, 8, len(ev.t)))
    off, k = fit_rotation_scale(*segment_displacements(noisy, WAYPOINTS, 1.0))
    assert abs((off - 12 + 180) % 360 - 180) < 3
    assert k == pytest.approx(0.42, rel=0.05)


def test_site_calibration_takes_the_median_over_map_walks():
    class W:
        def __init__(self, wp):
            self.waypoints = wp
    maps = [Prepared(W(WAYPOINTS), _events_along(WAYPOINTS, off, 0.4), []) for off in (8.0, 10.0, 12.0, 150.0)]
    cal = site_calibration(maps)
    assert cal["walks"] == 4
    assert 9.0 <= cal["heading_offset_deg"] <= 11.0  # the astray walk (150°) does not pull it
    assert cal["weinberg_k"] == pytest.approx(0.4, rel=1e-3)


def test_walk_calibration_fits_the_first_segments_or_the_whole_walk():
    """first-segment: the offset of the first ≥ 10 m; walk (the oracle): of all segments."""
    from client_sim.msft_eval import walk_calibration

    class W:
        waypoints = WAYPOINTS

    ev = _events_along(WAYPOINTS, 10.0, 0.4)
    turned = UncalibratedSteps(ev.t, ev.swing, np.where(ev.t > 10.0, ev.heading_deg - 20.0, ev.heading_deg))
    first = walk_calibration(Prepared(W(), turned, []))
    whole = walk_calibration(Prepared(W(), turned, []), None)
    assert first["heading_offset_deg"] == pytest.approx(10.0, abs=1e-6) and first["until_t"] == 10.0
    assert whole["until_t"] is None and 10.0 < whole["heading_offset_deg"] < 30.0


def test_calibration_window_leaves_the_last_segment_out():
    wp = np.array([[0.0, 0, 0], [5.0, 3, 0], [9.0, 3, 4]])
    assert calibration_window(wp, min_distance_m=100.0) == 5.0
    assert calibration_window(wp[:2], min_distance_m=100.0) == 5.0


def test_batches_and_errors(walk):
    ev = UncalibratedSteps(np.array([T0 - 0.5, T0 + 0.5, T0 + 2.5, T0 + 4.5]), np.full(4, 1.0), np.zeros(4))
    steps = steps_from_events(ev, 0.5, 0.0)
    scans = wifi_scans(walk)
    batches = [b.to_api() for b in make_batches(steps, scans, walk.t_start, walk.t_end, 2.0)]
    assert [b["seq"] for b in batches] == [0, 1, 2]
    assert [len(b["steps"]) for b in batches] == [1, 1, 1]  # the step before the start is left out
    assert [len(b["scans"]) for b in batches] == [1, 1, 0]
    assert batches[0]["steps"][0]["length_m"] == 0.5
    rows = errors_against(walk, [(T0 + 2, 13, 26), (T0 + 99, 0, 0)])
    assert len(rows) == 1 and rows[0]["error_m"] == pytest.approx(5.0)
    s = summarise([1, 2, 3, 4])
    assert s["mean"] == 2.5 and s["n"] == 4 and summarise([])["n"] == 0


def test_steps_without_declared_noise_send_no_std_fields():
    """``--step-noise none``: a phone that declares nothing, so the server's defaults apply."""
    ev = UncalibratedSteps(np.array([T0 + 0.5]), np.full(1, 1.0), np.zeros(1))
    silent = steps_from_events(ev, 0.5, 10.0, length_std_m=None, heading_std_deg=None)[0].to_api()
    assert set(silent) == {"t", "length_m", "heading_deg"} and silent["heading_deg"] == 10.0
    declared = steps_from_events(ev, 0.5, 10.0, length_std_m=0.06, heading_std_deg=13.0)[0].to_api()
    assert declared["length_std_m"] == 0.06 and declared["heading_std_deg"] == 13.0


def test_walk_selection(tmp_path):
    files = [tmp_path / f"w{i}.txt" for i in range(9)]
    maps, tests = default_split(9, 4)
    assert tests == [1, 5] and 1 not in maps and len(maps) == 7
    assert select_walks(files, "0,w3.txt,w4", []) == [files[0], files[3], files[4]]
    assert select_walks(files, None, [2]) == [files[2]]
    with pytest.raises(CliError, match="unknown walk 'nope'"):
        select_walks(files, "nope", [])


def test_heading_filter_does_not_take_a_moving_start_as_gyro_bias():
    """Real recordings start mid-walk: a turn in the first second is not a bias."""
    rate, n = 50.0, 500
    t = np.arange(n) / rate
    yaw_rate = np.where(t < 1.0, 0.3, 0.0)  # turning left in the first second, then straight
    heading = -np.degrees(np.cumsum(yaw_rate) / rate)  # clockwise heading (deg), starts at 0
    h = np.radians(heading)
    earth = np.array([0.0, 20.0, -40.0])  # north along +y
    mag = np.column_stack([earth[1] * -np.sin(h), earth[1] * np.cos(h), np.full(n, earth[2])])
    acc = np.column_stack([np.zeros(n), np.zeros(n), np.full(n, 9.81)])
    acc[:, 2] += 1.0 * np.sin(2 * np.pi * 2 * t)  # gait
    gyro = np.column_stack([np.zeros(n), np.zeros(n), yaw_rate])
    assert not is_still(gyro[:50], acc[:50])
    assert is_still(np.zeros((50, 3)), np.tile([0, 0, 9.81], (50, 1)))
    out = GyroMagKalman().run(ImuData(t, acc, gyro, mag))
    final = (out[-1] - heading[-1] + 180) % 360 - 180
    assert abs(final) < 3.0  # the old "first second is still" rule ended ~88° off here


def test_tables_from_walk_results():
    from client_sim.msft_eval import combine_folds, markdown, tabulate

    def walk(name, pdr, fp):
        return {"walk": name, "methods": {"pdr-only": [{"t": 0, "error_m": e} for e in pdr],
                                          "fingerprint-only": [{"t": 0, "error_m": e} for e in fp]}}
    walks = [walk("a", [1, 3], [10]), walk("b", [2], [20, 30])]
    table, per_walk = tabulate(walks)
    assert table["pdr-only"]["mean"] == 2.0 and table["fingerprint-only"]["n"] == 3
    assert per_walk == {"a": {"pdr-only": 2.0, "fingerprint-only": 10.0}, "b": {"pdr-only": 2.0,
                                                                              "fingerprint-only": 25.0}}
    fold = {"data_dir": "d", "map_walks": [], "test_walks": ["a"], "site_calibration": {}, "map": {}, "options": {}}
    both = combine_folds([fold | {"walks": walks[:1]}, fold | {"walks": walks[1:], "test_walks": ["b"]}])
    assert both["table"] == table and [w["fold"] for w in both["walks"]] == [0, 1]
    md = markdown(both)
    assert md.splitlines()[2].startswith("| pdr-only | 3 | 2.0 |")  # best mean first


def test_tables_give_the_share_of_scans_the_gate_refused():
    """Each walk records, per tracked method, [fixes refused, scans sent]; the table pools them
    over walks (3 of 40 = 7.5 %), and methods that send no scans show none."""
    from client_sim.msft_eval import markdown, tabulate

    walks = [{"walk": name, "methods": {"pdr-only": [{"t": 0, "error_m": 1.0}], "ekf": [{"t": 0, "error_m": 2.0}]},
              "refused": {"ekf": counts}} for name, counts in (("a", [1, 10]), ("b", [2, 30]))]
    table, _ = tabulate(walks)
    assert table["ekf"]["refused_pct"] == 7.5 and "refused_pct" not in table["pdr-only"]
    rows = markdown({"table": table, "per_walk_mean": {}}).splitlines()
    assert rows[0].endswith("| scans refused |")
    assert rows[2].startswith("| pdr-only |") and rows[2].endswith("| — |") and rows[3].endswith("| 7.5 % |")


def test_errors_against_scores_nees_when_the_estimate_has_a_covariance():
    """An estimate 3 m east of the truth with σ = 1.5 m on x: NEES (3/1.5)² = 4; without a
    covariance, no NEES; ``consistency`` averages the rows that have one."""
    from client_sim.msft import Walk, consistency

    empty = np.empty((0, 4))
    walk = Walk("w", empty, empty, empty, empty, waypoints=np.array([[0.0, 0.0, 0.0], [10.0, 10.0, 0.0]]))
    rows = errors_against(walk, [(5.0, 8.0, 0.0, [[2.25, 0.0], [0.0, 1.0]]), (6.0, 6.0, 0.0)])
    assert rows[0]["error_m"] == pytest.approx(3.0) and rows[0]["nees"] == pytest.approx(4.0)
    assert "nees" not in rows[1]
    assert consistency(rows) == {"nees_mean": 4.0, "nees_p50": 4.0}
    assert consistency(rows[1:]) == {}


def test_walks_without_a_span_are_left_out_and_said(tmp_path):
    """A walk with one waypoint has no span to score and no segment to calibrate on: it is left
    out with a message (it used to fail later in the calibration); none left at all is a usage error."""
    from client_sim.msft_eval import walks_with_a_span

    lines = FIXTURE.read_text().splitlines(keepends=True)
    waypoint_lines = [i for i, line in enumerate(lines) if "\tTYPE_WAYPOINT\t" in line]
    one = tmp_path / "one_waypoint.txt"
    one.write_text("".join(line for i, line in enumerate(lines) if i not in waypoint_lines[1:]))
    said: list[str] = []
    kept = walks_with_a_span([FIXTURE, one], "test", said.append)
    assert [w.name for w in kept] == ["msft_synthetic_walk"]
    assert len(said) == 1 and "one_waypoint" in said[0] and "1 waypoint" in said[0]
    with pytest.raises(CliError, match="no map walk has two waypoints"):
        walks_with_a_span([one], "map", said.append)
