"""Sites, floors, settings, revision and transmitters on a real database."""

from __future__ import annotations

import pytest
from sqlalchemy import insert
from sqlalchemy.exc import IntegrityError

from server.domain import Floor, NewSite, SiteCounts, Transmitter
from server.store import sites
from server.tables import Fingerprint

WALL = (0.0, 0.0, 10.0, 0.0)
AP1 = Transmitter("wifi:ap1", "wifi", floor=0, x=1.0, y=2.0, tx_power_dbm=-40.0, path_loss_exponent=2.5)
AP2 = Transmitter("wifi:ap2", "wifi")


def revision(db, site_id: int) -> str:
    with db.transaction() as s:
        site = sites.get_site(s, site_id)
        assert site is not None
        return site.revision


def test_a_site_round_trips_with_its_floors_and_transmitters(db):
    new = NewSite(
        name="museum",
        floors=(Floor(1, "first", 20.0, 10.0), Floor(0, "ground", walls=(WALL,))),
        transmitters=(AP1, AP2),
    )
    with db.transaction() as s:
        added = sites.add_site(s, new)
    with db.transaction() as s:
        site = sites.get_site(s, added.id)
        assert site == added
        assert site.name == "museum" and site.settings == {} and site.revision
        assert site.floors == (Floor(0, "ground", walls=(WALL,)), Floor(1, "first", 20.0, 10.0))  # by level
        assert sites.list_transmitters(s, added.id) == [AP1, AP2]
        assert sites.floor_ids(s, added.id) == {(0, 0), (0, 1)}
        assert sites.floor_walls(s, added.id, 0) == (WALL,)
        assert sites.floor_walls(s, added.id, 7) == ()
        assert sites.get_site(s, added.id + 1000) is None
        assert sites.site_exists(s, added.id) and not sites.site_exists(s, added.id + 1000)


def test_site_names_are_unique(db):
    with db.transaction() as s:
        sites.add_site(s, NewSite(name="twice"))
        assert sites.site_name_taken(s, "twice") and not sites.site_name_taken(s, "once")
    with pytest.raises(IntegrityError), db.transaction() as s:
        sites.add_site(s, NewSite(name="twice"))


def test_sites_are_listed_by_id_with_their_counts(db):
    with db.transaction() as s:
        first = sites.add_site(s, NewSite(name="a", transmitters=(AP1,)))
        second = sites.add_site(s, NewSite(name="b"))
        s.execute(insert(Fingerprint), [
            {"site_id": first.id, "source": source, "floor": 0, "x": 0.0, "y": 0.0, "rss": {"wifi:ap1": -50.0}}
            for source in ("survey", "survey", "crowd")
        ])
    with db.transaction() as s:
        assert [site.name for site in sites.list_sites(s)] == ["a", "b"]
        counts = sites.site_counts(s, [first.id, second.id])
        assert counts == {
            first.id: SiteCounts(transmitters=1, survey_fingerprints=2, crowd_fingerprints=1),
            second.id: SiteCounts(),
        }
        assert sites.site_counts(s, []) == {}


def test_settings_merge_and_renew_the_revision(db, site_id):
    before = revision(db, site_id)
    with db.transaction() as s:
        assert sites.merge_site_settings(s, site_id, {"crowdsourcing": True})
        assert sites.merge_site_settings(s, site_id, {"other": 1})
    with db.transaction() as s:
        assert sites.site_settings(s, site_id) == {"crowdsourcing": True, "other": 1}
        assert sites.merge_site_settings(s, site_id, {"crowdsourcing": False})
    with db.transaction() as s:
        site = sites.get_site(s, site_id)
        assert site is not None and site.settings == {"crowdsourcing": False, "other": 1}
        assert site.revision != before
        assert not sites.merge_site_settings(s, site_id + 1000, {"crowdsourcing": True})
        assert sites.site_settings(s, site_id + 1000) is None


def test_touch_renews_the_revision(db, site_id):
    before = revision(db, site_id)
    with db.transaction() as s:
        sites.touch_site(s, site_id)
    assert revision(db, site_id) != before


def test_upserted_transmitters_overwrite_known_ones_and_renew_the_revision(db, site_id):
    with db.transaction() as s:
        sites.upsert_transmitters(s, site_id, [AP1, AP2])
    before = revision(db, site_id)
    moved = Transmitter("wifi:ap2", "wifi", floor=0, x=5.0, y=5.0)
    cleared = Transmitter("wifi:ap1", "wifi")  # every field is overwritten, also with None
    with db.transaction() as s:
        sites.upsert_transmitters(s, site_id, [moved, cleared])
    after = revision(db, site_id)
    assert after != before
    with db.transaction() as s:
        assert sites.list_transmitters(s, site_id) == [cleared, moved]
        assert sites.positioned_transmitters(s, site_id) == [moved]
        sites.upsert_transmitters(s, site_id, [])  # nothing to do: the revision stays
    assert revision(db, site_id) == after


def test_heard_transmitters_are_registered_once_without_changing_the_revision(db, site_id):
    with db.transaction() as s:
        sites.upsert_transmitters(s, site_id, [AP1])
    before = revision(db, site_id)
    with db.transaction() as s:
        sites.add_heard_transmitters(s, site_id, ["wifi:ap1", "ble:door", "wifi:ap9"])
        sites.add_heard_transmitters(s, site_id, ["ble:door"])
    with db.transaction() as s:
        assert sites.list_transmitters(s, site_id) == [Transmitter("ble:door", "ble"), AP1, Transmitter("wifi:ap9", "wifi")]
    assert revision(db, site_id) == before


def test_the_site_context_holds_what_a_fix_depends_on(db):
    new = NewSite(name="ctx", floors=(Floor(0, walls=(WALL,)), Floor(1)), transmitters=(AP1, AP2))
    with db.transaction() as s:
        site = sites.add_site(s, new)
        sites.merge_site_settings(s, site.id, {"crowdsourcing": True})
    with db.transaction() as s:
        context = sites.site_context(s, site.id)
        assert context is not None
        assert context.revision == revision(db, site.id)
        assert context.settings == {"crowdsourcing": True}
        assert context.walls == {(0, 0): (WALL,), (0, 1): ()}
        assert context.transmitters == (AP1,)  # positioned ones only
        assert sites.site_context(s, site.id + 1000) is None


def test_deleting_a_site_deletes_what_it_holds(db):
    with db.transaction() as s:
        site = sites.add_site(s, NewSite(name="gone", floors=(Floor(0),), transmitters=(AP1,)))
        s.execute(insert(Fingerprint), [{"site_id": site.id, "source": "survey", "floor": 0, "x": 0.0, "y": 0.0, "rss": {}}])
    with db.transaction() as s:
        assert sites.delete_site(s, site.id)
    with db.transaction() as s:
        assert not sites.delete_site(s, site.id)
        assert sites.list_transmitters(s, site.id) == [] and sites.floor_ids(s, site.id) == set()
        assert sites.site_counts(s, [site.id]) == {site.id: SiteCounts()}
