"""What a real floor plan costs the PF: µs per step of PF-1000 without a plan, with the MSFT
site-1 F1 plan's walls (all-pairs test and ``floorplan.WallIndex``), and with walls plus the
walkable area; the tracker's store/load round trip with and without the plan's walls; and
how well the plan fits the walks (the bbox transform check of docs/msft-evaluation.md).

Run from the repository root:  python benchmarks/floorplan_cost.py ../shared/data/msft_site1_f1
Time figures are ratios against the no-plan step measured in the same process.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import shapely

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.tracker_cost import best_us  # noqa: E402
from client_sim.msft import read_walk  # noqa: E402
from client_sim.msft_eval import walk_files  # noqa: E402
from server.estimation import floorplan as floorplan_module  # noqa: E402
from server.estimation.floorplan import Walkable, read_plan  # noqa: E402
from server.estimation.tracking import ParticleFilterXYTracker, make_tracker, tracker_from_dict  # noqa: E402
from server.estimation.types import Step  # noqa: E402


def fit(data: Path, plan, area: Walkable) -> dict:
    """Waypoints (and the straight path between them) inside the floor outline / walkable space."""
    walks = [read_walk(f) for f in walk_files(data)]
    pts = np.vstack([w.waypoints[:, 1:] for w in walks])
    g = json.loads((data / "geojson_map.json").read_text())
    info = json.loads((data / "floor_info.json").read_text())["map_info"]
    outline = read_plan({"type": "FeatureCollection", "features": [f for f in g["features"]
                                                                   if f["properties"].get("type") == "floor"]},
                        bbox_size=(info["width"], info["height"]))
    assert outline.walkable is not None
    in_floor = Walkable(outline.walkable).contains(pts)
    inside = area.contains(pts)
    dense = np.vstack([w.truth_at(np.linspace(w.t_start, w.t_end, 200)) for w in walks])
    clearance = shapely.distance(area.geometry.boundary, shapely.points(pts))
    return {"walks": len(walks), "waypoints": len(pts), "in_floor_outline": round(float(in_floor.mean()), 4),
            "in_walkable": round(float(inside.mean()), 4), "in_stores": round(float((in_floor & ~inside).mean()), 4),
            "interpolated_path_in_walkable": round(float(area.contains(dense).mean()), 4),
            "clearance_p10_p50_m": [round(float(v), 2) for v in np.percentile(clearance, [10, 50])]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--repeat", type=int, default=300)
    a = ap.parse_args()
    info = json.loads((a.data / "floor_info.json").read_text())["map_info"]
    t0 = time.perf_counter()
    plan = read_plan(json.loads((a.data / "geojson_map.json").read_text()), bbox_size=(info["width"], info["height"]))
    assert plan.walkable is not None
    area = Walkable(plan.walkable)
    build_ms = (time.perf_counter() - t0) * 1e3
    print(f"plan: {len(plan.walls)} walls, {len(plan.walkable or [])} walkable rings, area {area.geometry.area:.0f} m²; "
          f"read + build {build_ms:.0f} ms")
    print("fit:", json.dumps(fit(a.data, plan, area)))

    rng = np.random.default_rng(0)
    steps = [Step(i, 0.7, float(h), 0.1, 5.0) for i, h in enumerate(rng.uniform(0, 360, a.repeat))]
    start = read_walk(walk_files(a.data)[0]).waypoints[0, 1:].tolist()  # in a corridor of the plan
    assert area.contains(np.array([start]))[0]
    cases = {}
    for label, walls, walkable, index in [("no plan", None, None, True), ("walls, all pairs", plan.walls, None, False),
                                          ("walls, index", plan.walls, None, True),
                                          ("walls + walkable, index", plan.walls, area, True)]:
        t = make_tracker("pf", start, np.eye(2), walls=walls, seed=0)
        assert isinstance(t, ParticleFilterXYTracker)
        t.set_walkable(walkable)
        threshold = floorplan_module.INDEX_FROM_WALLS
        floorplan_module.INDEX_FROM_WALLS = threshold if index else 10**9
        try:
            cases[label] = best_us(lambda i, t=t: t.predict(steps[i]), a.repeat)
        finally:
            floorplan_module.INDEX_FROM_WALLS = threshold
    base = cases["no plan"]
    for label, us in cases.items():
        print(f"pf predict, {label}: {us:.0f} µs ({us / base:.2f}× no plan)")
    for label, walls in [("no walls", None), ("plan walls", plan.walls)]:
        t = make_tracker("pf", start, np.eye(2), walls=walls, seed=0)
        size = len(json.dumps(t.to_dict()))
        us = best_us(lambda i, t=t: tracker_from_dict(json.loads(json.dumps(t.to_dict()))), 20)
        print(f"pf store+load, {label}: {us:.0f} µs, {size / 1e3:.0f} kB JSON")


if __name__ == "__main__":
    main()
