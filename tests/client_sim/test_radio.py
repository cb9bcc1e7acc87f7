"""Properties of the radio model: distance, walls, body shadowing, spatial correlation, seeds."""

from itertools import pairwise

import numpy as np
import pytest

from client_sim.radio import RadioModel, walls_crossed
from client_sim.world import Floor, RadioParams, Transmitter, World, corridor_loop, open_room

TX = Transmitter("wifi:02:00:00:00:00:01", "wifi", 0, 0.0, 0.0, -40.0, 2.5)


def world(walls=(), **radio) -> World:
    return World("t", (Floor(0, "f", 50, 50, tuple(walls)),), (TX,), (), (), RadioParams(**radio), seed=5)


def test_rss_falls_with_distance():
    m = RadioModel(world(shadowing_sigma_db=0.0))
    rss = [m.mean_rss(TX, d, 0.0, 0) for d in (1, 2, 5, 10, 20)]
    assert all(a > b for a, b in pairwise(rss))
    assert rss[0] == pytest.approx(-40.0)
    assert rss[2] - rss[3] == pytest.approx(10 * 2.5 * np.log10(2))  # log-distance slope


def test_each_wall_attenuates():
    walls = [(5, -10, 5, 10), (8, -10, 8, 10)]
    assert walls_crossed(0, 0, 10, 0, np.array(walls, float)) == 2
    free = RadioModel(world(shadowing_sigma_db=0.0)).mean_rss(TX, 10, 0, 0)
    walled = RadioModel(world(walls, shadowing_sigma_db=0.0, wall_loss_db=6.0)).mean_rss(TX, 10, 0, 0)
    assert free - walled == pytest.approx(12.0)


def test_body_shadowing_depends_on_heading():
    m = RadioModel(world(shadowing_sigma_db=0.0, body_loss_db=8.0))
    # transmitter at the origin, walker at (0, 10): facing it = heading 180°
    facing = m.mean_rss(TX, 0, 10, 0, heading_deg=180.0)
    away = m.mean_rss(TX, 0, 10, 0, heading_deg=0.0)
    side = m.mean_rss(TX, 0, 10, 0, heading_deg=90.0)
    assert facing - away == pytest.approx(8.0)
    assert away < side < facing


def test_shadowing_is_spatially_correlated():
    m = RadioModel(world(shadowing_sigma_db=4.0, shadowing_corr_m=3.0))
    rng = np.random.default_rng(0)
    pts = rng.uniform(5, 45, (300, 2))
    s = np.array([m.shadowing_db(TX, x, y, 0) for x, y in pts])
    near = np.array([m.shadowing_db(TX, x + 0.3, y, 0) for x, y in pts])
    far = np.array([m.shadowing_db(TX, x + 20, y, 0) for x, y in pts])
    assert 2.5 < s.std() < 5.5
    assert np.corrcoef(s, near)[0, 1] > 0.9
    assert abs(np.corrcoef(s, far)[0, 1]) < 0.3
    # the same spot gives the same mean on every visit
    assert m.shadowing_db(TX, 12.3, 4.5, 0) == m.shadowing_db(TX, 12.3, 4.5, 0)


def test_scans_are_deterministic_under_seed_and_differ_across_seeds():
    w = corridor_loop()
    a = RadioModel(w).scan(5, 1.25, 0, 90, "wifi", np.random.default_rng(7))
    b = RadioModel(w).scan(5, 1.25, 0, 90, "wifi", np.random.default_rng(7))
    c = RadioModel(w).scan(5, 1.25, 0, 90, "wifi", np.random.default_rng(8))
    assert a == b and a != c
    w2 = World(**{**w.__dict__, "seed": w.seed + 1})
    assert RadioModel(w).shadowing_db(w.transmitters[0], 5, 5, 0) != RadioModel(w2).shadowing_db(w.transmitters[0], 5, 5, 0)


def test_threshold_and_packet_loss():
    w = corridor_loop()
    m, rng = RadioModel(w), np.random.default_rng(1)
    scans = [m.scan(1.25, 1.25, 0, 0, "wifi", rng) for _ in range(200)]
    for s in scans:
        assert all(-130 <= v <= 0 and v >= w.radio.wifi_threshold_dbm for v in s.values())
    heard = {tx.id: np.mean([tx.id in s for s in scans]) for tx in w.transmitters if tx.kind == "wifi"}
    near, far = heard["wifi:02:00:00:00:00:00"], heard["wifi:02:00:00:00:00:07"]  # (7,8) vs (33,22)
    assert near > 0.6 and far < 0.3  # loss rises with distance (and walls)


def test_open_room_hears_everything_corridor_does_not():
    rng = np.random.default_rng(3)
    room = open_room()
    s = RadioModel(room).scan(10, 7, 0, 0, "wifi", rng)
    assert len(s) >= len([t for t in room.transmitters if t.kind == "wifi"]) - 1
    assert min(s.values()) > -80
