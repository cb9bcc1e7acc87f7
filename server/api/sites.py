"""Sites, their floors, transmitters and reference points (admin)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response, status
from sqlalchemy.orm import Session

from server import repositories as repo
from server.api.deps import DB, Admin
from server.schemas import (
    FingerprintCounts,
    FloorOut,
    ReferencePointOut,
    SiteIn,
    SiteOut,
    SitePatch,
    TransmitterList,
    TransmitterOut,
    undeclared_floors,
)
from server.tables import Site, Transmitter

router = APIRouter(prefix="/api/v1/sites", tags=["sites"])


def existing_site(s: Session, site_id: int) -> Site:
    site = repo.get_site(s, site_id)
    if site is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"site {site_id} does not exist")
    return site


def _site_out(site: Site, counts: dict[str, int]) -> SiteOut:
    return SiteOut(
        id=site.id,
        name=site.name,
        settings=dict(site.settings or {}),
        floors=[FloorOut.model_validate(f, from_attributes=True) for f in site.floors],
        transmitters=counts["transmitters"],
        reference_points=counts["reference_points"],
        fingerprints=FingerprintCounts(survey=counts["survey"], crowd=counts["crowd"]),
        created_at=site.created_at,
    )


def _transmitter_out(t: Transmitter) -> TransmitterOut:
    return TransmitterOut(
        id=t.tx_id, kind=t.kind, floor=t.floor, x=t.x, y=t.y,
        tx_power_dbm=t.tx_power_dbm, path_loss_exponent=t.path_loss_exponent,
    )


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SiteOut)
def create_site(body: SiteIn, db: DB, _: Admin) -> SiteOut:
    with db.transaction() as s:
        if repo.site_name_taken(s, body.name):
            raise HTTPException(status.HTTP_409_CONFLICT, f"a site named {body.name!r} already exists")
        site = repo.add_site(s, body)
        return _site_out(site, repo.site_counts(s, [site.id])[site.id])


@router.get("", response_model=list[SiteOut])
def list_sites(db: DB, _: Admin) -> list[SiteOut]:
    with db.transaction() as s:
        sites = repo.list_sites(s)
        counts = repo.site_counts(s, [site.id for site in sites])
        return [_site_out(site, counts[site.id]) for site in sites]


@router.get("/{site_id}", response_model=SiteOut)
def get_site(site_id: int, db: DB, _: Admin) -> SiteOut:
    with db.transaction() as s:
        site = existing_site(s, site_id)
        return _site_out(site, repo.site_counts(s, [site_id])[site_id])


@router.patch("/{site_id}", response_model=SiteOut)
def patch_site(site_id: int, body: SitePatch, db: DB, _: Admin) -> SiteOut:
    """Change site settings (given keys are merged into the stored ones)."""
    with db.transaction() as s:
        site = existing_site(s, site_id)
        repo.merge_site_settings(s, site_id, body.settings.model_dump(exclude_unset=True))
        s.refresh(site)
        return _site_out(site, repo.site_counts(s, [site_id])[site_id])


@router.delete("/{site_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_site(site_id: int, db: DB, _: Admin) -> Response:
    with db.transaction() as s:
        if not repo.delete_site(s, site_id):
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"site {site_id} does not exist")
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.put("/{site_id}/transmitters", response_model=list[TransmitterOut])
def put_transmitters(site_id: int, body: TransmitterList, db: DB, _: Admin) -> list[TransmitterOut]:
    """Upsert by id; answers every transmitter of the site."""
    ids = [t.id for t in body]
    if len(ids) != len(set(ids)):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "transmitter ids must be unique in one request")
    with db.transaction() as s:
        existing_site(s, site_id)
        if problem := undeclared_floors(repo.floor_levels(s, site_id), body):
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, problem)
        repo.upsert_transmitters(s, site_id, body)
        return [_transmitter_out(t) for t in repo.list_transmitters(s, site_id)]


@router.get("/{site_id}/transmitters", response_model=list[TransmitterOut])
def get_transmitters(site_id: int, db: DB, _: Admin) -> list[TransmitterOut]:
    with db.transaction() as s:
        existing_site(s, site_id)
        return [_transmitter_out(t) for t in repo.list_transmitters(s, site_id)]


@router.get("/{site_id}/reference-points", response_model=list[ReferencePointOut])
def get_reference_points(site_id: int, db: DB, _: Admin) -> list[ReferencePointOut]:
    with db.transaction() as s:
        existing_site(s, site_id)
        return [
            ReferencePointOut(label=rp.label, floor=rp.floor, x=rp.x, y=rp.y, fingerprints=n)
            for rp, n in repo.reference_points_with_counts(s, site_id)
        ]
