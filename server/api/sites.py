"""Sites, their floors, transmitters and reference points (admin)."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from server.api.deps import Admin, PathId, Sites
from server.domain import Floor, NewSite, SiteSummary, Transmitter
from server.schemas import (
    FingerprintCounts,
    FloorOut,
    ReferencePointOut,
    SiteIn,
    SiteOut,
    SitePatch,
    TransmitterIn,
    TransmitterList,
    TransmitterOut,
)

router = APIRouter(prefix="/api/v1/sites", tags=["sites"])


def _transmitter(t: TransmitterIn) -> Transmitter:
    return Transmitter(
        id=t.id, kind=t.kind, floor=t.floor, x=t.x, y=t.y, tx_power_dbm=t.tx_power_dbm, path_loss_exponent=t.path_loss_exponent,
    )


def _site_out(summary: SiteSummary) -> SiteOut:
    site, counts = summary.site, summary.counts
    return SiteOut(
        id=site.id,
        name=site.name,
        settings=dict(site.settings),
        floors=[
            FloorOut(level=f.level, name=f.name, width_m=f.width_m, height_m=f.height_m, walls=[list(w) for w in f.walls])
            for f in site.floors
        ],
        transmitters=counts.transmitters,
        reference_points=counts.reference_points,
        fingerprints=FingerprintCounts(survey=counts.survey_fingerprints, crowd=counts.crowd_fingerprints),
        created_at=site.created_at,
    )


def _transmitter_out(t: Transmitter) -> TransmitterOut:
    return TransmitterOut(
        id=t.id, kind=t.kind, floor=t.floor, x=t.x, y=t.y, tx_power_dbm=t.tx_power_dbm, path_loss_exponent=t.path_loss_exponent,
    )


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SiteOut)
def create_site(body: SiteIn, sites: Sites, _: Admin) -> SiteOut:
    new = NewSite(
        name=body.name,
        floors=tuple(
            Floor(level=f.level, name=f.name, width_m=f.width_m, height_m=f.height_m, walls=tuple(f.walls))
            for f in body.floors
        ),
        transmitters=tuple(_transmitter(t) for t in body.transmitters),
    )
    return _site_out(sites.create(new))


@router.get("", response_model=list[SiteOut])
def list_sites(sites: Sites, _: Admin) -> list[SiteOut]:
    return [_site_out(summary) for summary in sites.list_sites()]


@router.get("/{site_id}", response_model=SiteOut)
def get_site(site_id: PathId, sites: Sites, _: Admin) -> SiteOut:
    return _site_out(sites.get(site_id))


@router.patch("/{site_id}", response_model=SiteOut)
def patch_site(site_id: PathId, body: SitePatch, sites: Sites, _: Admin) -> SiteOut:
    """Change site settings (given keys are merged into the stored ones)."""
    return _site_out(sites.update_settings(site_id, body.settings.model_dump(exclude_unset=True)))


@router.delete("/{site_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_site(site_id: PathId, sites: Sites, _: Admin) -> Response:
    sites.delete(site_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.put("/{site_id}/transmitters", response_model=list[TransmitterOut])
def put_transmitters(site_id: PathId, body: TransmitterList, sites: Sites, _: Admin) -> list[TransmitterOut]:
    """Upsert by id; answers every transmitter of the site."""
    return [_transmitter_out(t) for t in sites.put_transmitters(site_id, [_transmitter(t) for t in body])]


@router.get("/{site_id}/transmitters", response_model=list[TransmitterOut])
def get_transmitters(site_id: PathId, sites: Sites, _: Admin) -> list[TransmitterOut]:
    return [_transmitter_out(t) for t in sites.transmitters(site_id)]


@router.get("/{site_id}/reference-points", response_model=list[ReferencePointOut])
def get_reference_points(site_id: PathId, sites: Sites, _: Admin) -> list[ReferencePointOut]:
    return [
        ReferencePointOut(label=rp.label, floor=rp.floor, x=rp.x, y=rp.y, fingerprints=rp.fingerprints)
        for rp in sites.reference_points(site_id)
    ]
