"""Survey uploads, the reference points they create and the fingerprints they store.

Survey and crowd fingerprints share one table, kept apart by ``source``; reference
points are keyed by ``(building, floor, label)`` or ``(building, floor, x, y)`` to the millimetre.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import Any

from sqlalchemy import func, insert, select, update
from sqlalchemy.orm import Session

from server.domain import CoverageCell, FingerprintRecord, ReferencePointSummary, SurveyOutcome
from server.store._results import tuples
from server.store.sites import add_heard_transmitters
from server.tables import Fingerprint, ReferencePoint, SurveyUpload


def find_upload(s: Session, site_id: int, idempotency_key: str) -> SurveyOutcome | None:
    """The outcome stored for an earlier upload with this key, as a replay."""
    found = upload_of_key(s, site_id, idempotency_key)
    return None if found is None else found[0]


def upload_of_key(s: Session, site_id: int, idempotency_key: str) -> tuple[SurveyOutcome, str | None] | None:
    """The outcome stored for an earlier upload with this key (as a replay) and its request's hash
    (None: stored before requests were hashed)."""
    row = s.execute(
        select(SurveyUpload.result, SurveyUpload.request_hash)
        .where(SurveyUpload.site_id == site_id, SurveyUpload.idempotency_key == idempotency_key)
    ).first()
    if row is None:
        return None
    stored: dict[str, Any] = row.result
    return SurveyOutcome(
        accepted=stored["accepted"], reference_points=stored["reference_points"],
        new_reference_points=stored["new_reference_points"], skipped=stored.get("skipped", 0), replayed=True,
        already_stored=stored.get("already_stored", 0),
    ), row.request_hash


def source_rows(s: Session, site_id: int, source: str) -> list[tuple[int, int]]:
    """The rows of the file ``source`` that earlier uploads stored: sorted, merged ``[first, end)`` ranges."""
    stored: list[list[Any] | None] = list(s.scalars(
        select(SurveyUpload.source_rows).where(SurveyUpload.site_id == site_id, SurveyUpload.source == source)
    ))
    ranges = [(int(a), int(b)) for upload_rows in stored for a, b in upload_rows or ()]
    return merge_ranges(ranges)


def merge_ranges(ranges: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    merged: list[tuple[int, int]] = []
    for a, b in sorted(ranges):
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def ranges_of(rows: Iterable[int]) -> list[tuple[int, int]]:
    """Row numbers as merged ``[first, end)`` ranges."""
    return merge_ranges((r, r + 1) for r in rows)


def reference_point_key(fp: FingerprintRecord) -> str:
    """Fingerprints sharing (building, floor, key) share a reference point: by label, else by position (mm)."""
    return f"label:{fp.label}" if fp.label is not None else f"xy:{round(fp.x, 3):g},{round(fp.y, 3):g}"


def add_survey(
    s: Session, site_id: int, fingerprints: Sequence[FingerprintRecord], idempotency_key: str | None, skipped: int,
    *, request_hash: str | None = None, source: str | None = None, rows: Sequence[int] = (), already_stored: int = 0,
) -> SurveyOutcome:
    """Store a validated survey: reference points, unseen transmitters and fingerprints, in bulk.
    ``rows``: the file rows of ``source`` the fingerprints are (remembered, so no later upload stores them again)."""
    keys = [(fp.building, fp.floor, reference_point_key(fp)) for fp in fingerprints]
    rp_ids, created = _ensure_reference_points(s, site_id, fingerprints, keys)
    add_heard_transmitters(s, site_id, {tx for fp in fingerprints for tx in fp.rss})
    upload = SurveyUpload(
        site_id=site_id, idempotency_key=idempotency_key, request_hash=request_hash, source=source,
        source_rows=None if source is None else [list(r) for r in ranges_of(rows)],
    )
    s.add(upload)
    s.flush()
    if not fingerprints:  # every row had been stored by an earlier upload of the file
        upload.result = {"accepted": 0, "reference_points": 0, "new_reference_points": 0, "skipped": skipped,
                         "already_stored": already_stored}
        return SurveyOutcome(0, 0, 0, skipped, already_stored=already_stored)
    s.execute(
        insert(Fingerprint),
        [
            {
                "site_id": site_id,
                "source": "survey",
                "reference_point_id": rp_ids[key],
                "upload_id": upload.id,
                "building": fp.building,
                "floor": fp.floor,
                "x": fp.x,
                "y": fp.y,
                "heading_deg": None if fp.heading_deg is None else fp.heading_deg % 360.0,
                "t": fp.t,
                "device": fp.device,
                "rss": dict(fp.rss),
                "samples": 1,
            }
            for fp, key in zip(fingerprints, keys, strict=True)
        ],
    )
    _recentre_labelled_points(s, [rp_ids[k] for k in set(keys) if k[2].startswith("label:")])
    outcome = SurveyOutcome(
        accepted=len(fingerprints), reference_points=len(set(keys)), new_reference_points=created, skipped=skipped,
        already_stored=already_stored,
    )
    upload.result = {
        "accepted": outcome.accepted,
        "reference_points": outcome.reference_points,
        "new_reference_points": outcome.new_reference_points,
        "skipped": outcome.skipped,
        "already_stored": outcome.already_stored,
    }
    return outcome


#: a reference point's identity on its site: (building, floor, key)
RpKey = tuple[int, int, str]


def _ensure_reference_points(
    s: Session, site_id: int, fingerprints: Sequence[FingerprintRecord], keys: list[RpKey]
) -> tuple[dict[RpKey, int], int]:
    """Ids of the reference points for ``keys``, creating the missing ones; also how many were new."""
    ids: dict[RpKey, int] = {}
    stored = select(ReferencePoint.id, ReferencePoint.building, ReferencePoint.floor, ReferencePoint.key).where(
        ReferencePoint.site_id == site_id)
    for rp_id, building, floor, rp_key in tuples(s.execute(stored)):
        ids[(building, floor, rp_key)] = rp_id
    first: dict[RpKey, FingerprintRecord] = {}
    for fp, key in zip(fingerprints, keys, strict=True):
        if key not in ids:
            first.setdefault(key, fp)
    if first:
        created = s.execute(
            insert(ReferencePoint).returning(
                ReferencePoint.id, ReferencePoint.building, ReferencePoint.floor, ReferencePoint.key),
            [
                {"site_id": site_id, "building": building, "floor": floor, "key": rp_key, "label": fp.label,
                 "x": fp.x, "y": fp.y}
                for (building, floor, rp_key), fp in first.items()
            ],
        )
        for rp_id, building, floor, rp_key in created:
            ids[(building, floor, rp_key)] = rp_id
    return ids, len(first)


def _recentre_labelled_points(s: Session, rp_ids: list[int]) -> None:
    """A labelled reference point sits at the mean position of its fingerprints."""
    for chunk in _chunks(rp_ids, 500):
        means = s.execute(
            select(Fingerprint.reference_point_id, func.avg(Fingerprint.x), func.avg(Fingerprint.y))
            .where(Fingerprint.reference_point_id.in_(chunk))
            .group_by(Fingerprint.reference_point_id)
        ).all()
        s.execute(update(ReferencePoint), [{"id": i, "x": x, "y": y} for i, x, y in means])


def _chunks(items: list[int], size: int) -> Iterator[list[int]]:
    for i in range(0, len(items), size):
        yield items[i : i + size]


def reference_points(s: Session, site_id: int) -> list[ReferencePointSummary]:
    """The site's reference points with how many fingerprints each holds, by (building, floor)."""
    counts = (
        select(Fingerprint.reference_point_id, func.count().label("n"))
        .where(Fingerprint.site_id == site_id)
        .group_by(Fingerprint.reference_point_id)
        .subquery()
    )
    rows = s.execute(
        select(ReferencePoint.label, ReferencePoint.floor, ReferencePoint.x, ReferencePoint.y, func.coalesce(counts.c.n, 0),
               ReferencePoint.building)
        .outerjoin(counts, counts.c.reference_point_id == ReferencePoint.id)
        .where(ReferencePoint.site_id == site_id)
        .order_by(ReferencePoint.building, ReferencePoint.floor, ReferencePoint.id)
    )
    return [ReferencePointSummary(*row) for row in tuples(rows)]


def coverage(s: Session, site_id: int, transmitter_id: str, floor: int, building: int = 0) -> list[CoverageCell]:
    """Per reference point of ``floor`` of ``building`` and per source: its fingerprints, how many heard ``transmitter_id``
    and their mean RSS, in one query (JSON access as each backend spells it: SQLite ``JSON_EXTRACT``,
    PostgreSQL ``->>``; a fingerprint that did not hear the transmitter gives NULL, which ``count`` and
    ``avg`` skip). Crowd fingerprints belong to no reference point: one cell with ``reference_point_id`` None."""
    rss = Fingerprint.rss[transmitter_id].as_float()
    rows = s.execute(
        select(
            Fingerprint.reference_point_id, ReferencePoint.label, ReferencePoint.x, ReferencePoint.y,
            Fingerprint.source, func.count(), func.count(rss), func.avg(rss),
        )
        .outerjoin(ReferencePoint, ReferencePoint.id == Fingerprint.reference_point_id)
        .where(Fingerprint.site_id == site_id, Fingerprint.building == building, Fingerprint.floor == floor)
        .group_by(
            Fingerprint.reference_point_id, ReferencePoint.label, ReferencePoint.x, ReferencePoint.y, Fingerprint.source,
        )
        .order_by(Fingerprint.reference_point_id, Fingerprint.source)
    )
    return [
        CoverageCell(rp_id, label, x, y, source, int(n), int(heard), None if mean is None else float(mean))
        for rp_id, label, x, y, source, n, heard, mean in tuples(rows)
    ]


def stream_training_rows(
    s: Session, site_id: int, include_crowd: bool, chunk: int = 500,
) -> Iterator[FingerprintRecord]:
    """The site's fingerprints (survey ones only, unless ``include_crowd``) with their reference point's
    label, in id order, fetched ``chunk`` rows at a time (a server-side cursor on PostgreSQL): a large
    site's rows never exist as Python objects all at once (training builds its matrix from them)."""
    query = (
        select(
            Fingerprint.x, Fingerprint.y, Fingerprint.floor, Fingerprint.rss, Fingerprint.heading_deg,
            Fingerprint.t, Fingerprint.device, ReferencePoint.label, Fingerprint.building,
        )
        .outerjoin(ReferencePoint, ReferencePoint.id == Fingerprint.reference_point_id)
        .where(Fingerprint.site_id == site_id)
        .order_by(Fingerprint.id)
        .execution_options(yield_per=chunk)
    )
    if not include_crowd:
        query = query.where(Fingerprint.source == "survey")
    for row in s.execute(query):
        values: tuple[Any, ...] = tuple(row)
        yield FingerprintRecord(*values)
