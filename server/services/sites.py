"""Sites: create, read, change settings, delete; their transmitters and reference points."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from sqlalchemy.orm import Session

from server.db import Database
from server.domain import (
    CoverageCell,
    NewSite,
    ReferencePointSummary,
    Site,
    SiteSummary,
    Transmitter,
    undeclared_floors,
)
from server.errors import Conflict, Invalid, NotFound
from server.store import sites as store
from server.store import surveys as survey_store


class SiteService:
    def __init__(self, db: Database):
        self._db = db

    def create(self, new: NewSite) -> SiteSummary:
        """Site names are unique."""
        with self._db.transaction() as s:
            if store.site_name_taken(s, new.name):
                raise Conflict(f"a site named {new.name!r} already exists")
            return _with_counts(s, store.add_site(s, new))

    def list_sites(self) -> list[SiteSummary]:
        with self._db.transaction() as s:
            sites = store.list_sites(s)
            counts = store.site_counts(s, [site.id for site in sites])
            return [SiteSummary(site, counts[site.id]) for site in sites]

    def get(self, site_id: int) -> SiteSummary:
        with self._db.transaction() as s:
            return _summary(s, site_id)

    def update_settings(self, site_id: int, changes: Mapping[str, Any]) -> SiteSummary:
        """Merge ``changes`` into the stored settings (keys not given keep their value)."""
        with self._db.transaction() as s:
            if not store.merge_site_settings(s, site_id, changes):
                raise _no_site(site_id)
            return _summary(s, site_id)

    def delete(self, site_id: int) -> None:
        """The site and everything of it: floors, transmitters, surveys, models, sessions."""
        with self._db.transaction() as s:
            if not store.delete_site(s, site_id):
                raise _no_site(site_id)

    def put_transmitters(self, site_id: int, items: Sequence[Transmitter]) -> list[Transmitter]:
        """Upsert by id; answers every transmitter of the site."""
        ids = [t.id for t in items]
        if len(ids) != len(set(ids)):
            raise Invalid("transmitter ids must be unique in one request")
        with self._db.transaction() as s:
            _existing(s, site_id)
            if problem := undeclared_floors(store.floor_ids(s, site_id), items):
                raise Invalid(problem)
            store.upsert_transmitters(s, site_id, items)
            return store.list_transmitters(s, site_id)

    def transmitters(self, site_id: int) -> list[Transmitter]:
        with self._db.transaction() as s:
            _existing(s, site_id)
            return store.list_transmitters(s, site_id)

    def reference_points(self, site_id: int) -> list[ReferencePointSummary]:
        with self._db.transaction() as s:
            _existing(s, site_id)
            return survey_store.reference_points(s, site_id)

    def coverage(self, site_id: int, transmitter_id: str, floor: int, building: int = 0) -> list[CoverageCell]:
        """Measured RSS of one transmitter per reference point of a floor of a building (and over the floor's
        crowd fingerprints); a transmitter no fingerprint heard gives ``heard`` 0 everywhere."""
        with self._db.transaction() as s:
            _existing(s, site_id)
            return survey_store.coverage(s, site_id, transmitter_id, floor, building)


def _no_site(site_id: int) -> NotFound:
    return NotFound(f"site {site_id} does not exist")


def _existing(s: Session, site_id: int) -> None:
    if not store.site_exists(s, site_id):
        raise _no_site(site_id)


def _summary(s: Session, site_id: int) -> SiteSummary:
    site = store.get_site(s, site_id)
    if site is None:
        raise _no_site(site_id)
    return _with_counts(s, site)


def _with_counts(s: Session, site: Site) -> SiteSummary:
    return SiteSummary(site, store.site_counts(s, [site.id])[site.id])
