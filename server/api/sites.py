"""Sites, their floors, transmitters and reference points (admin)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from server.api.deps import Admin, PathId, Sites
from server.domain import Floor, NewSite, SiteSummary, Transmitter
from server.schemas import (
    MAX_BUILDING,
    TX_ID_PATTERN,
    CoverageCount,
    CoverageOut,
    CoveragePointOut,
    FingerprintCounts,
    FloorIn,
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
        building=t.building,
    )


def _floor_out(f: Floor) -> FloorOut:
    return FloorOut(
        level=f.level, building=f.building, name=f.name, width_m=f.width_m, height_m=f.height_m,
        walls=[list(w) for w in f.walls],
        walkable=None if f.walkable is None else [[list(p) for p in ring] for ring in f.walkable],
    )


def _floor(f: FloorIn) -> Floor:
    return Floor(
        level=f.level, building=f.building, name=f.name, width_m=f.width_m, height_m=f.height_m, walls=tuple(f.walls),
        walkable=None if f.walkable is None else tuple(tuple(ring) for ring in f.walkable),
    )


def _site_out(summary: SiteSummary) -> SiteOut:
    site, counts = summary.site, summary.counts
    return SiteOut(
        id=site.id,
        name=site.name,
        settings=dict(site.settings),
        floors=[_floor_out(f) for f in site.floors],
        transmitters=counts.transmitters,
        reference_points=counts.reference_points,
        fingerprints=FingerprintCounts(survey=counts.survey_fingerprints, crowd=counts.crowd_fingerprints),
        created_at=site.created_at,
    )


def _transmitter_out(t: Transmitter) -> TransmitterOut:
    return TransmitterOut(
        id=t.id, kind=t.kind, floor=t.floor, building=t.building, x=t.x, y=t.y, tx_power_dbm=t.tx_power_dbm,
        path_loss_exponent=t.path_loss_exponent,
    )


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SiteOut)
def create_site(body: SiteIn, sites: Sites, _: Admin) -> SiteOut:
    new = NewSite(
        name=body.name,
        floors=tuple(_floor(f) for f in body.floors),
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
        ReferencePointOut(label=rp.label, floor=rp.floor, building=rp.building, x=rp.x, y=rp.y,
                          fingerprints=rp.fingerprints)
        for rp in sites.reference_points(site_id)
    ]


@router.get("/{site_id}/coverage", response_model=CoverageOut)
def get_coverage(
    site_id: PathId,
    sites: Sites,
    _: Admin,
    transmitter: Annotated[str, Query(pattern=TX_ID_PATTERN, description="The transmitter's id.")],
    floor: Annotated[int, Query(ge=-20, le=200, description="Floor level.")],
    building: Annotated[int, Query(ge=0, le=MAX_BUILDING, description="The floor's building (default 0).")] = 0,
) -> CoverageOut:
    """Measured coverage (extension): per reference point of the floor, how many survey fingerprints it
    holds, how many heard the transmitter and their mean RSS; the floor's crowd fingerprints together."""
    cells = sites.coverage(site_id, transmitter, floor, building)
    crowd = [c for c in cells if c.reference_point_id is None]
    crowd_n = sum(c.fingerprints for c in crowd)
    crowd_heard = sum(c.heard for c in crowd)
    crowd_mean = (
        sum(c.mean_rss_dbm * c.heard for c in crowd if c.mean_rss_dbm is not None) / crowd_heard if crowd_heard else None
    )
    return CoverageOut(
        transmitter=transmitter,
        floor=floor,
        building=building,
        reference_points=[
            CoveragePointOut(label=c.label, x=c.x, y=c.y, fingerprints=c.fingerprints, heard=c.heard,
                             mean_rss_dbm=c.mean_rss_dbm)
            for c in cells if c.reference_point_id is not None and c.x is not None and c.y is not None
        ],
        crowd=CoverageCount(fingerprints=crowd_n, heard=crowd_heard, mean_rss_dbm=crowd_mean),
    )
