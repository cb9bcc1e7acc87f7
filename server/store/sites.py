"""Sites with their floors, settings and revision, and their transmitters.

A site's ``revision`` is renewed (``touch_site``) whenever something a fix depends on
changes: settings, positioned transmitters, the active model (``store.models``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from sqlalchemy import delete, func, insert, select, update
from sqlalchemy.orm import Session, selectinload

from server.domain import Floor, FloorId, NewSite, Polygon, Site, SiteContextRecord, SiteCounts, Transmitter, Wall
from server.store._results import changed, tuples
from server.tables import Fingerprint, ReferencePoint, new_revision
from server.tables import Floor as FloorRow
from server.tables import Site as SiteRow
from server.tables import Transmitter as TransmitterRow

# --- sites and floors -------------------------------------------------------------------------


def _walls(stored: Iterable[Iterable[float]] | None) -> tuple[Wall, ...]:
    return tuple((float(x1), float(y1), float(x2), float(y2)) for x1, y1, x2, y2 in stored or ())


def _walkable(stored: Iterable[Iterable[Iterable[float]]] | None) -> tuple[Polygon, ...] | None:
    return None if stored is None else tuple(tuple((float(x), float(y)) for x, y in ring) for ring in stored)


def _floor(row: FloorRow) -> Floor:
    return Floor(level=row.level, name=row.name, width_m=row.width_m, height_m=row.height_m, walls=_walls(row.walls),
                 building=row.building, walkable=_walkable(row.walkable))


def _site(row: SiteRow) -> Site:
    return Site(
        id=row.id, name=row.name, settings=dict(row.settings or {}), floors=tuple(_floor(f) for f in row.floors),
        created_at=row.created_at, revision=row.revision,
    )


def add_site(s: Session, new: NewSite) -> Site:
    floors = [
        FloorRow(building=f.building, level=f.level, name=f.name, width_m=f.width_m, height_m=f.height_m,
                 walls=[list(w) for w in f.walls],
                 walkable=None if f.walkable is None else [[list(p) for p in ring] for ring in f.walkable])
        for f in new.floors
    ]
    row = SiteRow(name=new.name, floors=floors)
    s.add(row)
    s.flush()
    upsert_transmitters(s, row.id, new.transmitters)
    s.refresh(row)  # the transmitters renewed the revision
    return _site(row)


def site_name_taken(s: Session, name: str) -> bool:
    return bool(s.scalar(select(func.count()).select_from(SiteRow).where(SiteRow.name == name)))


def site_exists(s: Session, site_id: int) -> bool:
    return s.scalar(select(SiteRow.id).where(SiteRow.id == site_id)) is not None


def lock_site(s: Session, site_id: int) -> bool:
    """Whether the site exists; on PostgreSQL its row stays locked until the transaction ends, so
    writers of one site's surveys take turns (SQLite: ``Database.transaction(write=True)`` does)."""
    return s.scalar(select(SiteRow.id).where(SiteRow.id == site_id).with_for_update()) is not None


def get_site(s: Session, site_id: int) -> Site | None:
    row = s.scalar(
        select(SiteRow).where(SiteRow.id == site_id).options(selectinload(SiteRow.floors))
        .execution_options(populate_existing=True)
    )
    return None if row is None else _site(row)


def list_sites(s: Session) -> list[Site]:
    rows = s.scalars(
        select(SiteRow).order_by(SiteRow.id).options(selectinload(SiteRow.floors)).execution_options(populate_existing=True)
    )
    return [_site(row) for row in rows]


def delete_site(s: Session, site_id: int) -> bool:
    """Delete the site and (by cascade) everything of it; False when there was no such site."""
    return changed(s.execute(delete(SiteRow).where(SiteRow.id == site_id))) == 1


def site_counts(s: Session, site_ids: Iterable[int]) -> dict[int, SiteCounts]:
    """Transmitter, reference point and survey / crowd fingerprint counts per site."""
    ids = list(site_ids)
    counts: dict[int, dict[str, int]] = {i: {} for i in ids}
    if not ids:
        return {}
    for site_id, n in s.execute(
        select(TransmitterRow.site_id, func.count()).where(TransmitterRow.site_id.in_(ids)).group_by(TransmitterRow.site_id)
    ):
        counts[site_id]["transmitters"] = n
    for site_id, n in s.execute(
        select(ReferencePoint.site_id, func.count())
        .where(ReferencePoint.site_id.in_(ids))
        .group_by(ReferencePoint.site_id)
    ):
        counts[site_id]["reference_points"] = n
    for site_id, source, n in s.execute(
        select(Fingerprint.site_id, Fingerprint.source, func.count())
        .where(Fingerprint.site_id.in_(ids))
        .group_by(Fingerprint.site_id, Fingerprint.source)
    ):
        counts[site_id][f"{source}_fingerprints"] = n
    return {site_id: SiteCounts(**found) for site_id, found in counts.items()}


def floor_ids(s: Session, site_id: int) -> set[FloorId]:
    """The site's declared floors as (building, level) pairs."""
    return set(tuples(s.execute(select(FloorRow.building, FloorRow.level).where(FloorRow.site_id == site_id))))


def floor_walls(s: Session, site_id: int, level: int, building: int = 0) -> tuple[Wall, ...]:
    """The wall segments of one floor of a site (none when the floor is not declared)."""
    return _walls(s.scalar(select(FloorRow.walls).where(
        FloorRow.site_id == site_id, FloorRow.building == building, FloorRow.level == level)))


# --- settings and revision --------------------------------------------------------------------


def site_settings(s: Session, site_id: int) -> dict[str, Any] | None:
    """A site's settings, or None when the site does not exist."""
    row = s.execute(select(SiteRow.settings).where(SiteRow.id == site_id)).first()
    return None if row is None else dict(row[0] or {})


def merge_site_settings(s: Session, site_id: int, changes: Mapping[str, Any]) -> bool:
    """Merge ``changes`` into the stored settings and renew the revision; False when there
    is no such site. A compare-and-set on the revision makes concurrent merges each see
    the other's keys instead of overwriting them."""
    while True:
        row = s.execute(select(SiteRow.settings, SiteRow.revision).where(SiteRow.id == site_id)).first()
        if row is None:
            return False
        merged = {**(row.settings or {}), **changes}
        done = s.execute(
            update(SiteRow)
            .where(SiteRow.id == site_id, SiteRow.revision == row.revision)
            .values(settings=merged, revision=new_revision())
            .execution_options(synchronize_session=False)
        )
        if changed(done) == 1:
            return True


def touch_site(s: Session, site_id: int) -> None:
    """Give the site a new revision: something a fix depends on changed (see ``tables.Site.revision``)."""
    s.execute(update(SiteRow).where(SiteRow.id == site_id).values(revision=new_revision()))


def site_context(s: Session, site_id: int) -> SiteContextRecord | None:
    """Settings, walls and positioned transmitters with the revision they are valid for (None: no site)."""
    site = s.execute(select(SiteRow.revision, SiteRow.settings).where(SiteRow.id == site_id)).first()
    if site is None:
        return None
    floors = s.execute(select(FloorRow.building, FloorRow.level, FloorRow.walls).where(FloorRow.site_id == site_id))
    return SiteContextRecord(
        revision=site.revision,
        settings=dict(site.settings or {}),
        walls={(building, level): _walls(walls) for building, level, walls in tuples(floors)},
        transmitters=tuple(positioned_transmitters(s, site_id)),
    )


# --- transmitters -----------------------------------------------------------------------------

_TRANSMITTER_FIELDS = ("kind", "floor", "x", "y", "tx_power_dbm", "path_loss_exponent", "building")
#: the columns of a ``Transmitter``, in its fields' order
_TRANSMITTER = select(
    TransmitterRow.tx_id, TransmitterRow.kind, TransmitterRow.floor, TransmitterRow.x, TransmitterRow.y,
    TransmitterRow.tx_power_dbm, TransmitterRow.path_loss_exponent, TransmitterRow.building,
)


def upsert_transmitters(s: Session, site_id: int, items: Iterable[Transmitter]) -> None:
    """Insert new transmitters and overwrite every stored field of known ones; renews the revision."""
    items = list(items)
    if not items:
        return
    touch_site(s, site_id)
    known = {t.tx_id: t for t in s.scalars(select(TransmitterRow).where(TransmitterRow.site_id == site_id))}
    for item in items:
        fields = {name: getattr(item, name) for name in _TRANSMITTER_FIELDS}
        row = known.get(item.id)
        if row is None:
            s.add(TransmitterRow(site_id=site_id, tx_id=item.id, **fields))
        else:
            for name, value in fields.items():
                setattr(row, name, value)
    s.flush()


def add_heard_transmitters(s: Session, site_id: int, tx_ids: Iterable[str]) -> None:
    """Register transmitters first heard in a survey (no position or radio parameters, so
    nothing a fix depends on changes)."""
    known = set(s.scalars(select(TransmitterRow.tx_id).where(TransmitterRow.site_id == site_id)))
    new = sorted(set(tx_ids) - known)
    if new:
        s.execute(
            insert(TransmitterRow),
            [{"site_id": site_id, "tx_id": tx, "kind": tx.split(":", 1)[0]} for tx in new],
        )


def list_transmitters(s: Session, site_id: int) -> list[Transmitter]:
    rows = s.execute(_TRANSMITTER.where(TransmitterRow.site_id == site_id).order_by(TransmitterRow.tx_id))
    return [Transmitter(*row) for row in rows]


def positioned_transmitters(s: Session, site_id: int) -> list[Transmitter]:
    """The transmitters with a known position (what multilateration and propagation can use)."""
    rows = s.execute(_TRANSMITTER.where(TransmitterRow.site_id == site_id, TransmitterRow.x.is_not(None)))
    return [Transmitter(*row) for row in rows]
