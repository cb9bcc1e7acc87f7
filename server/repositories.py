"""All reads and writes of the database. Nothing outside this module builds SQL.

Functions take an open `Session` inside the caller's transaction, so one request's
effects commit (or roll back) together. The per-batch path of tracking sessions takes a
Core `Connection` instead and runs statements built once at import: a batch is the
service's hottest request, and the ORM's per-statement work was most of its cost.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from datetime import UTC, datetime

from sqlalchemy import Connection, bindparam, delete, func, insert, select, update
from sqlalchemy.orm import Session

from server.schemas import FingerprintIn, FloorIn, SiteIn, TransmitterIn
from server.tables import (
    ApiKey,
    Fingerprint,
    Floor,
    Model,
    ModelArtifact,
    ReferencePoint,
    Site,
    SurveyUpload,
    Transmitter,
    new_revision,
)

# --- API keys ----------------------------------------------------------------------------


def add_api_key(s: Session, name: str, scope: str, key_hash: str) -> ApiKey:
    key = ApiKey(name=name, scope=scope, key_hash=key_hash)
    s.add(key)
    s.flush()
    return key


def find_api_key(s: Session, key_hash: str) -> ApiKey | None:
    return s.scalar(select(ApiKey).where(ApiKey.key_hash == key_hash, ApiKey.revoked_at.is_(None)))


def list_api_keys(s: Session) -> Sequence[ApiKey]:
    return s.scalars(select(ApiKey).order_by(ApiKey.id)).all()


def revoke_api_key(s: Session, key_id: int) -> bool:
    result = s.execute(
        update(ApiKey)
        .where(ApiKey.id == key_id, ApiKey.revoked_at.is_(None))
        .values(revoked_at=datetime.now(UTC))
    )
    return result.rowcount == 1


# --- sites, floors, transmitters ----------------------------------------------------------


def add_site(s: Session, body: SiteIn) -> Site:
    site = Site(name=body.name, floors=[_floor(f) for f in body.floors])
    s.add(site)
    s.flush()
    upsert_transmitters(s, site.id, body.transmitters)
    return site


def _floor(f: FloorIn) -> Floor:
    return Floor(level=f.level, name=f.name, width_m=f.width_m, height_m=f.height_m, walls=[list(w) for w in f.walls])


def site_name_taken(s: Session, name: str) -> bool:
    return s.scalar(select(func.count()).select_from(Site).where(Site.name == name)) > 0


def get_site(s: Session, site_id: int) -> Site | None:
    return s.get(Site, site_id)


def list_sites(s: Session) -> Sequence[Site]:
    return s.scalars(select(Site).order_by(Site.id)).all()


def delete_site(s: Session, site_id: int) -> bool:
    return s.execute(delete(Site).where(Site.id == site_id)).rowcount == 1


def site_counts(s: Session, site_ids: Iterable[int]) -> dict[int, dict[str, int]]:
    """Transmitter, reference point and fingerprint (survey/crowd) counts per site."""
    ids = list(site_ids)
    counts = {i: {"transmitters": 0, "reference_points": 0, "survey": 0, "crowd": 0} for i in ids}
    if not ids:
        return counts
    for site_id, n in s.execute(
        select(Transmitter.site_id, func.count()).where(Transmitter.site_id.in_(ids)).group_by(Transmitter.site_id)
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
        counts[site_id][source] = n
    return counts


def floor_levels(s: Session, site_id: int) -> set[int]:
    return set(s.scalars(select(Floor.level).where(Floor.site_id == site_id)))


def touch_site(s: Session, site_id: int) -> None:
    """Give the site a new revision: something a fix depends on changed (see ``Site.revision``)."""
    s.execute(update(Site).where(Site.id == site_id).values(revision=new_revision()))


def upsert_transmitters(s: Session, site_id: int, items: Iterable[TransmitterIn]) -> None:
    """Insert new transmitters and overwrite the stored fields of known ones."""
    items = list(items)
    if not items:
        return
    touch_site(s, site_id)
    known = {t.tx_id: t for t in s.scalars(select(Transmitter).where(Transmitter.site_id == site_id))}
    for item in items:
        fields = item.model_dump(exclude={"id"})
        row = known.get(item.id)
        if row is None:
            s.add(Transmitter(site_id=site_id, tx_id=item.id, **fields))
        else:
            for name, value in fields.items():
                setattr(row, name, value)
    s.flush()


def list_transmitters(s: Session, site_id: int) -> Sequence[Transmitter]:
    return s.scalars(select(Transmitter).where(Transmitter.site_id == site_id).order_by(Transmitter.tx_id)).all()


def reference_points_with_counts(s: Session, site_id: int) -> list[tuple[ReferencePoint, int]]:
    counts = (
        select(Fingerprint.reference_point_id, func.count().label("n"))
        .where(Fingerprint.site_id == site_id)
        .group_by(Fingerprint.reference_point_id)
        .subquery()
    )
    rows = s.execute(
        select(ReferencePoint, func.coalesce(counts.c.n, 0))
        .outerjoin(counts, counts.c.reference_point_id == ReferencePoint.id)
        .where(ReferencePoint.site_id == site_id)
        .order_by(ReferencePoint.floor, ReferencePoint.id)
    )
    return [(rp, n) for rp, n in rows]


# --- surveys --------------------------------------------------------------------------------


def find_upload(s: Session, site_id: int, idempotency_key: str) -> SurveyUpload | None:
    return s.scalar(
        select(SurveyUpload).where(SurveyUpload.site_id == site_id, SurveyUpload.idempotency_key == idempotency_key)
    )


def reference_point_key(fp: FingerprintIn) -> str:
    """Fingerprints sharing (floor, key) share a reference point: by label, else by position (mm)."""
    return f"label:{fp.label}" if fp.label is not None else f"xy:{round(fp.x, 3):g},{round(fp.y, 3):g}"


def add_survey(
    s: Session, site_id: int, fingerprints: Sequence[FingerprintIn], idempotency_key: str | None, skipped: int
) -> dict[str, int]:
    """Store a validated survey: reference points, unseen transmitters and fingerprints, in bulk."""
    keys = [(fp.floor, reference_point_key(fp)) for fp in fingerprints]
    rp_ids, created = _ensure_reference_points(s, site_id, fingerprints, keys)
    _ensure_transmitters(s, site_id, {tx for fp in fingerprints for tx in fp.rss})
    upload = SurveyUpload(site_id=site_id, idempotency_key=idempotency_key)
    s.add(upload)
    s.flush()
    s.execute(
        insert(Fingerprint),
        [
            {
                "site_id": site_id,
                "source": "survey",
                "reference_point_id": rp_ids[key],
                "upload_id": upload.id,
                "floor": fp.floor,
                "x": fp.x,
                "y": fp.y,
                "heading_deg": None if fp.heading_deg is None else fp.heading_deg % 360.0,
                "t": fp.t,
                "device": fp.device,
                "rss": fp.rss,
                "samples": 1,
            }
            for fp, key in zip(fingerprints, keys)
        ],
    )
    _recentre_labelled_points(s, [rp_ids[k] for k in set(keys) if k[1].startswith("label:")])
    result = {
        "accepted": len(fingerprints),
        "reference_points": len(set(keys)),
        "new_reference_points": created,
        "skipped": skipped,
    }
    upload.result = result
    return result


def _ensure_reference_points(
    s: Session, site_id: int, fingerprints: Sequence[FingerprintIn], keys: list[tuple[int, str]]
) -> tuple[dict[tuple[int, str], int], int]:
    """Ids of the reference points for ``keys``, creating the missing ones; also how many were new."""
    ids: dict[tuple[int, str], int] = {}
    for rp_id, floor, key in s.execute(
        select(ReferencePoint.id, ReferencePoint.floor, ReferencePoint.key).where(ReferencePoint.site_id == site_id)
    ):
        ids[(floor, key)] = rp_id
    first: dict[tuple[int, str], FingerprintIn] = {}
    for fp, key in zip(fingerprints, keys):
        if key not in ids:
            first.setdefault(key, fp)
    if first:
        created = s.execute(
            insert(ReferencePoint).returning(ReferencePoint.id, ReferencePoint.floor, ReferencePoint.key),
            [
                {"site_id": site_id, "floor": floor, "key": key, "label": fp.label, "x": fp.x, "y": fp.y}
                for (floor, key), fp in first.items()
            ],
        )
        for rp_id, floor, key in created:
            ids[(floor, key)] = rp_id
    return ids, len(first)


def _recentre_labelled_points(s: Session, rp_ids: list[int]) -> None:
    """A labelled reference point sits at the mean position of its fingerprints."""
    if not rp_ids:
        return
    for chunk in _chunks(rp_ids, 500):
        means = s.execute(
            select(Fingerprint.reference_point_id, func.avg(Fingerprint.x), func.avg(Fingerprint.y))
            .where(Fingerprint.reference_point_id.in_(chunk))
            .group_by(Fingerprint.reference_point_id)
        ).all()
        s.execute(update(ReferencePoint), [{"id": i, "x": x, "y": y} for i, x, y in means])


def _ensure_transmitters(s: Session, site_id: int, tx_ids: set[str]) -> None:
    """Register transmitters first heard in a survey (no position or radio parameters)."""
    known = set(s.scalars(select(Transmitter.tx_id).where(Transmitter.site_id == site_id)))
    new = sorted(tx_ids - known)
    if new:
        s.execute(
            insert(Transmitter),
            [{"site_id": site_id, "tx_id": tx, "kind": tx.split(":", 1)[0]} for tx in new],
        )


# --- tracking sessions ----------------------------------------------------------------------


def floor_walls(s: Session, site_id: int, level: int) -> list[list[float]]:
    """The wall segments of one floor of a site ([] when the floor is not declared)."""
    return s.scalar(select(Floor.walls).where(Floor.site_id == site_id, Floor.level == level)) or []


def site_settings(s: Session, site_id: int) -> dict | None:
    """A site's settings, or None when the site does not exist."""
    row = s.execute(select(Site.settings).where(Site.id == site_id)).first()
    return None if row is None else dict(row[0] or {})


def model_site(s: Session, model_id: int) -> int | None:
    return s.scalar(select(Model.site_id).where(Model.id == model_id))


def merge_site_settings(s: Session, site_id: int, changes: dict) -> bool:
    """Merge ``changes`` into the stored settings. A compare-and-set on the revision makes
    concurrent merges each see the other's keys instead of overwriting them."""
    while True:
        row = s.execute(select(Site.settings, Site.revision).where(Site.id == site_id)).first()
        if row is None:
            return False
        merged = {**(row.settings or {}), **changes}
        done = s.execute(
            update(Site)
            .where(Site.id == site_id, Site.revision == row.revision)
            .values(settings=merged, revision=new_revision())
            .execution_options(synchronize_session=False)
        )
        if done.rowcount == 1:
            return True


def _chunks(items: list[int], size: int) -> Iterable[list[int]]:
    for i in range(0, len(items), size):
        yield items[i : i + size]



# --- models ---------------------------------------------------------------------------------


def add_model(
    s: Session, site_id: int, algorithm: str, params: dict, use_heading: bool, kinds: list[str], include_crowd: bool
) -> Model:
    model = Model(
        site_id=site_id, algorithm=algorithm, params=params, use_heading=use_heading, kinds=kinds,
        include_crowd=include_crowd, status="queued",
    )
    s.add(model)
    s.flush()
    return model


def get_model(s: Session, site_id: int, model_id: int) -> Model | None:
    return s.scalar(select(Model).where(Model.site_id == site_id, Model.id == model_id))


def list_models(s: Session, site_id: int) -> Sequence[Model]:
    return s.scalars(select(Model).where(Model.site_id == site_id).order_by(Model.id)).all()


_SERVING = (
    select(Model.id, Model.algorithm, Model.status, ModelArtifact.sha256)
    .outerjoin(ModelArtifact, ModelArtifact.model_id == Model.id)
    .where(Model.site_id == bindparam("site_id"))
)
_SERVING_ACTIVE = _SERVING.where(Model.active.is_(True))
_SERVING_CHOSEN = _SERVING.where(Model.id == bindparam("model_id"))


def serving_model(s: Session | Connection, site_id: int, model_id: int | None) -> tuple[int, str, str, str | None] | None:
    """(id, algorithm, status, artifact SHA-256) of ``model_id`` on the site, or of the site's active model."""
    if model_id is None:
        row = s.execute(_SERVING_ACTIVE, {"site_id": site_id}).first()
    else:
        row = s.execute(_SERVING_CHOSEN, {"site_id": site_id, "model_id": model_id}).first()
    return tuple(row) if row else None


def claim_next_model(s: Session, stale_before: datetime) -> int | None:
    """Take the oldest queued job (or one whose worker died) with a compare-and-set, so two
    workers never train the same model."""
    candidates = s.scalars(
        select(Model.id)
        .where(
            (Model.status == "queued")
            | ((Model.status == "training") & (Model.claimed_at < stale_before))
        )
        .order_by(Model.id)
        .limit(5)
    ).all()
    for model_id in candidates:
        taken = s.execute(
            update(Model)
            .where(
                Model.id == model_id,
                (Model.status == "queued") | ((Model.status == "training") & (Model.claimed_at < stale_before)),
            )
            .values(status="training", claimed_at=datetime.now(UTC), error=None)
        )
        if taken.rowcount == 1:
            return model_id
    return None


def training_job(s: Session, model_id: int) -> Model | None:
    return s.get(Model, model_id)


def training_rows(s: Session, site_id: int, include_crowd: bool) -> list[dict]:
    """Fingerprints as plain dicts for the estimation code, with their reference point's label."""
    query = (
        select(
            Fingerprint.x, Fingerprint.y, Fingerprint.floor, Fingerprint.rss, Fingerprint.heading_deg,
            Fingerprint.device, Fingerprint.t, ReferencePoint.label,
        )
        .outerjoin(ReferencePoint, ReferencePoint.id == Fingerprint.reference_point_id)
        .where(Fingerprint.site_id == site_id)
        .order_by(Fingerprint.id)
    )
    if not include_crowd:
        query = query.where(Fingerprint.source == "survey")
    return [row._asdict() for row in s.execute(query)]


def site_context(s: Session, site_id: int) -> dict | None:
    """Everything a fix on the site depends on, with the revision it is valid for (None: no site)."""
    site = s.execute(select(Site.revision, Site.settings).where(Site.id == site_id)).first()
    if site is None:
        return None
    floors = s.execute(select(Floor.level, Floor.walls).where(Floor.site_id == site_id)).all()
    return {
        "revision": site.revision,
        "settings": dict(site.settings or {}),
        "walls": {level: walls or [] for level, walls in floors},
        "transmitters": positioned_transmitters(s, site_id),
        "active_model": serving_model(s, site_id, None),
    }


def positioned_transmitters(s: Session, site_id: int) -> list[dict]:
    """Transmitters with a known position, as plain dicts for the propagation model."""
    rows = s.execute(
        select(
            Transmitter.tx_id.label("id"), Transmitter.kind, Transmitter.floor, Transmitter.x, Transmitter.y,
            Transmitter.tx_power_dbm, Transmitter.path_loss_exponent,
        ).where(Transmitter.site_id == site_id, Transmitter.x.is_not(None))
    )
    return [row._asdict() for row in rows]


def finish_training(
    s: Session, model_id: int, blob: bytes, sha256: str, trained_on: int, metrics: dict | None
) -> None:
    s.add(ModelArtifact(model_id=model_id, sha256=sha256, blob=blob))
    s.execute(
        update(Model)
        .where(Model.id == model_id)
        .values(status="ready", trained_on=trained_on, metrics=metrics, error=None)
    )


def requeue_model(s: Session, model_id: int) -> None:
    s.execute(update(Model).where(Model.id == model_id, Model.status == "training").values(status="queued"))


def fail_training(s: Session, model_id: int, error: str) -> None:
    s.execute(update(Model).where(Model.id == model_id).values(status="failed", error=error[:2000]))


def has_active_model(s: Session, site_id: int) -> bool:
    return s.scalar(select(func.count()).select_from(Model).where(Model.site_id == site_id, Model.active)) > 0


def activate_model(s: Session, site_id: int, model_id: int) -> None:
    """Make ``model_id`` the site's only active model. Readers see the old or the new one,
    never none: both statements commit together."""
    s.execute(update(Model).where(Model.site_id == site_id, Model.active, Model.id != model_id).values(active=False))
    s.execute(update(Model).where(Model.id == model_id).values(active=True))
    touch_site(s, site_id)


def model_artifact(s: Session, model_id: int) -> ModelArtifact | None:
    return s.get(ModelArtifact, model_id)
