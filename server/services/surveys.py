"""Survey ingestion: parse, check against the site, store in one transaction."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from server.db import Database
from server.domain import FingerprintRecord, SurveyOutcome
from server.errors import Invalid, NotFound
from server.store import sites as site_store
from server.store import surveys as store
from server.survey_formats import parse_survey


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
    ) -> SurveyOutcome:
        """Store a survey, or on ``dry_run`` run every check and the full write, then roll back.
        An upload with the ``idempotency_key`` of a stored one gets that one's outcome again."""
        parsed = parse_survey(body, content_type, fmt, self.max_rows)
        with self._db.transaction(rollback_only=dry_run) as s:
            if not site_store.site_exists(s, site_id):
                raise NotFound(f"site {site_id} does not exist")
            if idempotency_key is not None and (done := store.find_upload(s, site_id, idempotency_key)):
                return done
            check_floors(site_store.floor_levels(s, site_id), parsed.fingerprints)
            stored = store.add_survey(s, site_id, parsed.fingerprints, idempotency_key, parsed.skipped)
        return dataclasses.replace(stored, dry_run=dry_run)


def check_floors(declared: set[int], fingerprints: Sequence[FingerprintRecord]) -> None:
    """A site that declares its floors accepts fingerprints on those floors only."""
    if not declared:
        return
    bad = [
        {"row": i, "field": "floor", "msg": f"floor {fp.floor} is not a floor of this site {sorted(declared)}"}
        for i, fp in enumerate(fingerprints)
        if fp.floor not in declared
    ]
    if bad:
        raise Invalid(bad[:100])
