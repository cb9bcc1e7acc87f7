"""Survey ingestion: parse, check against the site, store in one transaction."""

from __future__ import annotations

import bisect
import dataclasses
import hashlib
from collections.abc import Sequence

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.db import Database
from server.domain import FingerprintRecord, FloorId, SurveyOutcome, floor_names
from server.errors import Conflict, Invalid, NotFound
from server.store import sites as site_store
from server.store import surveys as store
from server.survey_formats import ParsedSurvey, parse_survey


class SurveyService:
    """``max_rows``: the most fingerprints one upload may hold."""

    def __init__(self, db: Database, max_rows: int):
        self._db = db
        self.max_rows = max_rows

    def ingest(
        self,
        site_id: int,
        body: bytes,
        content_type: str,
        fmt: str | None,
        *,
        idempotency_key: str | None = None,
        dry_run: bool = False,
        source: str | None = None,
        first_row: int = 0,
    ) -> SurveyOutcome:
        """Store a survey, or on ``dry_run`` run every check and the full write, then roll back.

        An upload with the ``idempotency_key`` of a stored one gets that one's outcome again if it
        is the same request (format and body), and is a `Conflict` if it is another. ``source``
        names the file the body is a part of, whose data rows start at ``first_row``: rows of the
        file that an earlier upload stored are not stored again, whatever the chunking."""
        request_hash = hashlib.sha256(
            f"{fmt}|{content_type.split(';')[0].strip().lower()}|{source}|{first_row}\n".encode() + body
        ).hexdigest()
        parsed = parse_survey(body, content_type, fmt, self.max_rows)
        for attempt in range(3):
            try:
                with self._db.transaction(rollback_only=dry_run, write=True) as s:
                    outcome = self._store(s, site_id, parsed, idempotency_key, request_hash, source, first_row)
                return dataclasses.replace(outcome, dry_run=dry_run) if not outcome.replayed else outcome
            except IntegrityError:
                # a concurrent upload created the same reference point, transmitter or key first: again,
                # now seeing it (a replay, or a 409 for another body with the key)
                if attempt == 2:
                    raise
        raise AssertionError("unreachable")

    def _store(
        self, s: Session, site_id: int, parsed: ParsedSurvey, idempotency_key: str | None, request_hash: str,
        source: str | None, first_row: int,
    ) -> SurveyOutcome:
        if not site_store.lock_site(s, site_id):
            raise NotFound(f"site {site_id} does not exist")
        if idempotency_key is not None and (done := store.upload_of_key(s, site_id, idempotency_key)):
            outcome, stored_hash = done
            if stored_hash is not None and stored_hash != request_hash:
                raise Conflict(
                    f"Idempotency-Key {idempotency_key!r} was used before with another request (body, format or "
                    "source): a key may only repeat the same request; use a new key for a new request"
                )
            return outcome
        check_floors(site_store.floor_ids(s, site_id), parsed.fingerprints)
        fingerprints, rows, already = parsed.fingerprints, [first_row + parsed.row_of(i) for i in
                                                             range(len(parsed.fingerprints))], 0
        if source is not None:
            stored = store.source_rows(s, site_id, source)
            starts = [a for a, _ in stored]
            fresh = []
            for i, row in enumerate(rows):
                at = bisect.bisect_right(starts, row) - 1
                if not (at >= 0 and row < stored[at][1]):
                    fresh.append(i)
            already = len(rows) - len(fresh)
            fingerprints, rows = [fingerprints[i] for i in fresh], [rows[i] for i in fresh]
        return store.add_survey(
            s, site_id, fingerprints, idempotency_key, parsed.skipped,
            request_hash=request_hash, source=source, rows=rows, already_stored=already,
        )


def check_floors(declared: set[FloorId], fingerprints: Sequence[FingerprintRecord]) -> None:
    """A site that declares its floors accepts fingerprints on those (building, level) floors only."""
    if not declared:
        return
    bad = [
        {"row": i, "field": "floor",
         "msg": f"{_floor_name(fp.building, fp.floor)} is not a floor of this site {floor_names(declared)}"}
        for i, fp in enumerate(fingerprints)
        if (fp.building, fp.floor) not in declared
    ]
    if bad:
        raise Invalid(bad[:100])


def _floor_name(building: int, level: int) -> str:
    return f"floor {level}" if building == 0 else f"building {building} floor {level}"
