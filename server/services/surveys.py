"""Survey ingestion: parse, check against the site, store in one transaction."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from server import repositories as repo
from server.db import Database
from server.errors import Invalid, NotFound
from server.schemas import FingerprintIn, SurveyResult
from server.survey_formats import parse_survey


@dataclass
class Ingested:
    result: SurveyResult
    replayed: bool = False


def ingest_survey(
    db: Database,
    site_id: int,
    body: bytes,
    content_type: str,
    fmt: str | None,
    *,
    max_rows: int,
    idempotency_key: str | None = None,
    dry_run: bool = False,
) -> Ingested:
    """Store a survey, or on ``dry_run`` run every check and the full write, then roll back."""
    parsed = parse_survey(body, content_type, fmt, max_rows)
    with db.transaction(rollback_only=dry_run) as s:
        if repo.get_site(s, site_id) is None:
            raise NotFound(f"site {site_id} does not exist")
        if idempotency_key is not None and (done := repo.find_upload(s, site_id, idempotency_key)):
            return Ingested(SurveyResult(**done.result), replayed=True)
        check_floors(repo.floor_levels(s, site_id), parsed.fingerprints)
        stored = repo.add_survey(s, site_id, parsed.fingerprints, idempotency_key, parsed.skipped)
    return Ingested(SurveyResult(**stored, dry_run=dry_run))


def check_floors(declared: set[int], fingerprints: Sequence[FingerprintIn]) -> None:
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
