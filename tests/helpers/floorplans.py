"""A small GeoJSON floor plan in longitude/latitude, with the site coordinates it stands for.

A 200 m × 100 m floor (the outline, ``properties.type = "floor"``) with a closed store (an
obstacle) at x 50–150, y 40–100; the bbox transform onto 200 × 100 m gives back the metres.
"""

from __future__ import annotations

LON0, LAT0, DLON, DLAT = 120.0, 30.0, 0.002, 0.001
WIDTH_M, HEIGHT_M = 200.0, 100.0
STORE = (50.0, 40.0, 150.0, 100.0)


def lonlat(x: float, y: float) -> list[float]:
    """Site metres → the plan's lon/lat (the inverse of the bbox transform)."""
    return [LON0 + x / WIDTH_M * DLON, LAT0 + y / HEIGHT_M * DLAT]


def ring(*xy: tuple[float, float]) -> list[list[float]]:
    pts = [lonlat(x, y) for x, y in xy]
    return pts + [pts[0]]


def plan_geojson(extra: tuple = ()) -> dict:
    x0, y0, x1, y1 = STORE
    return {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"type": "floor", "name": "F1"},
         "geometry": {"type": "MultiPolygon", "coordinates": [[ring((0, 0), (200, 0), (200, 100), (0, 100))]]}},
        {"type": "Feature", "properties": {"name": "store"},
         "geometry": {"type": "Polygon", "coordinates": [ring((x0, y0), (x1, y0), (x1, y1), (x0, y1))]}},
        {"type": "Feature", "properties": {"name": "label"}, "geometry": {"type": "Point", "coordinates": lonlat(5, 5)}},
        *extra,
    ]}


def in_store(x: float, y: float) -> bool:
    x0, y0, x1, y1 = STORE
    return x0 < x < x1 and y0 < y < y1
