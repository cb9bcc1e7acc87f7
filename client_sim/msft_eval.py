"""Real-data evaluation on the Microsoft site-1 floor-1 walks, over HTTP only.

    python -m client_sim msft ../shared/data/msft_site1_f1 [--map-walks ...] [--test-walks ...]

1. Map: every WiFi scan (and, with ``--ble``, every 1-s window of iBeacon readings) of
   the map walks is placed at the waypoint-interpolated position of its time and
   uploaded as a survey to a new site; a model is trained and awaited.
2. PDR calibration: the project's on-phone PDR (:mod:`client_sim.pdr`) gives steps
   with magnetic headings and Weinberg swings (``Options.heading`` picks the heading
   filter; for "quasi-static" the site's undisturbed field comes from the map walks).
   The heading offset (magnetic north → the map's +y) and the Weinberg k come, by
   default, from the *map* walks (all their
   waypoint segments: the offset and k a site's app would ship with) — nothing of a
   test walk's truth but its start. ``--calibration first-segment`` instead fits both
   per test walk on its first waypoint segments covering ≥ 10 m (an app's initial
   alignment); errors inside that window are then left out for every method.
3. Replay: per test walk and filter a tracking session opened at the first waypoint
   (``initial``) is fed batches of steps + scans every ``--interval`` s of phone
   time; PDR alone is dead reckoning of the same steps from the first waypoint;
   fingerprinting alone is one ``locate`` per scan.
4. Errors: each estimate against the waypoint-interpolated truth at its time,
   inside the waypoints' time span only.
"""

from __future__ import annotations

import asyncio
import json
import math
import secrets
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .batches import Scan, make_batches
from .errors import EXIT_USAGE, CliError
from .http_client import ApiError, LocalizerClient
from .msft import (
    UncalibratedSteps,
    Walk,
    beacon_scans,
    calibration_window,
    consistency,
    dead_reckon,
    detect_steps,
    errors_against,
    field_reference,
    fit_rotation_scale,
    read_walk,
    segment_displacements,
    steps_from_events,
    summarise,
    survey_rows,
    wifi_scans,
)
from .pdr import PdrConfig, PdrStep
from .pdr.step_length import weinberg

FILTERS = ("skpf", "ekf", "ukf", "kf", "pf", "fkf")


def walk_files(data_dir: Path) -> list[Path]:
    d = Path(data_dir)
    if (d / "path_data_files").is_dir():
        d = d / "path_data_files"
    return sorted(d.glob("*.txt"))


def select_walks(files: list[Path], spec: str | None, default: list[int]) -> list[Path]:
    """``spec``: comma list of indices (into the sorted file list) or file names/stems."""
    if not spec:
        return [files[i] for i in default]
    out = []
    by_stem = {f.stem: f for f in files}
    for item in (s.strip() for s in spec.split(",")):
        if not item:
            continue
        if item.isdigit() and int(item) < len(files):
            out.append(files[int(item)])
        elif Path(item).stem in by_stem:
            out.append(by_stem[Path(item).stem])
        else:
            raise CliError(f"unknown walk {item!r}", EXIT_USAGE)
    return out


def default_split(n: int, every: int = 4) -> tuple[list[int], list[int]]:
    """Every ``every``-th walk (1, 5, 9, …) is a test walk, the rest build the map."""
    test = list(range(1, n, every))
    return [i for i in range(n) if i not in test], test


@dataclass(frozen=True)
class Prepared:
    """One walk read once: its truth, its steps before calibration and its scans."""

    walk: Walk
    events: UncalibratedSteps
    scans: list[Scan]


def prepare(walk: Walk, config: PdrConfig, max_age_s: float, ble: bool) -> Prepared:
    scans = wifi_scans(walk, max_age_s)
    if ble:
        scans = sorted(scans + beacon_scans(walk), key=lambda s: s["t"])
    return Prepared(walk, detect_steps(walk, config), scans)


def pdr_config(heading: str, map_walks: list[Walk]) -> PdrConfig:
    """The phones' PDR for this site: ``heading`` filter; for "quasi-static" the site's
    undisturbed field from its map walks (:func:`field_reference`), as the app ships it."""
    if heading != "quasi-static":
        return PdrConfig(heading=heading)
    field_ut, dip_deg = field_reference(map_walks)
    return PdrConfig(heading=heading, field_ut=round(field_ut, 2), dip_deg=round(dip_deg, 2))


def _circular_median(deg: list[float]) -> float:
    """The angle minimising the summed absolute angular distance (1° grid)."""
    a = np.radians(np.asarray(deg))
    grid = np.radians(np.arange(0, 360, 0.5))
    cost = np.abs(np.angle(np.exp(1j * (grid[:, None] - a[None, :])))).sum(axis=1)
    return float(np.degrees(grid[np.argmin(cost)]))


def _robust_std(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def site_calibration(maps: list[Prepared], min_segment_m: float = 3.0) -> dict:
    """Heading offset and Weinberg k from the map walks: per walk a least-squares fit
    over all its waypoint segments, then the median across walks (a few walks have a
    heading filter that went astray; the median ignores them).

    The step noise the phone declares comes from the same walks: ``heading_std_deg``
    is the robust spread of the per-segment heading residual after the offset, and
    ``length_std_m`` the robust spread of the per-segment length ratio times the
    median step length (segments shorter than ``min_segment_m`` are skipped)."""
    offsets, ks = [], []
    for p in maps:
        pdr, true = segment_displacements(p.events, p.walk.waypoints, 1.0)
        if len(pdr) and np.linalg.norm(true, axis=1).sum() > 5.0:
            off, k = fit_rotation_scale(pdr, true)
            offsets.append(off)
            ks.append(k)
    if not offsets:
        return {"heading_offset_deg": 0.0, "weinberg_k": 0.45, "heading_std_deg": 8.0, "heading_white_std_deg": 5.0,
                "length_std_m": 0.1,
                "walks": 0}
    off, k = _circular_median(offsets), float(np.median(ks))
    spread = np.degrees(np.abs(np.angle(np.exp(1j * np.radians(np.asarray(offsets) - off)))))
    h_res: list[float] = []
    h_white: list[float] = []  # about each walk's own median: the part a bias state does not explain
    l_res: list[float] = []
    lengths: list[float] = []
    for p in maps:
        pdr, true = segment_displacements(p.events, p.walk.waypoints, k)
        walk_res = []
        for a, b in zip(pdr, true, strict=True):
            lb, la = float(np.linalg.norm(b)), float(np.linalg.norm(a))
            if lb < min_segment_m or la == 0:
                continue
            d = math.degrees(math.atan2(a[0], a[1])) + off - math.degrees(math.atan2(b[0], b[1]))
            walk_res.append((d + 180) % 360 - 180)
            l_res.append(la / lb)
        h_res += walk_res
        if len(walk_res) >= 3:
            h_white += (np.asarray(walk_res) - float(np.median(walk_res))).tolist()
        lengths.extend(weinberg(p.events.swing, np.zeros_like(p.events.swing), k))
    return {"heading_offset_deg": round(off, 2), "weinberg_k": round(k, 4), "walks": len(offsets),
            "heading_std_deg": round(_robust_std(h_res), 1) if h_res else 8.0,
            "heading_white_std_deg": round(_robust_std(h_white), 1) if h_white else 5.0,
            "length_std_m": round(_robust_std(l_res) * float(np.median(lengths)), 3) if l_res else 0.1,
            "segments": len(h_res), "offset_abs_dev_p50_deg": round(float(np.median(spread)), 1),
            "k_range": [round(float(min(ks)), 3), round(float(max(ks)), 3)]}


def walk_calibration(p: Prepared, min_distance_m: float | None = 10.0) -> dict:
    """Heading offset and Weinberg k of one walk, fitted on its first waypoint segments covering
    ``min_distance_m`` (an app's initial alignment), or on all of them with None (an oracle: a
    diagnostic of how the trackers use a PDR as good as the walk allows)."""
    t_cal = None if min_distance_m is None else calibration_window(p.walk.waypoints, min_distance_m)
    pdr, true = segment_displacements(p.events, p.walk.waypoints, 1.0, t_until=t_cal)
    off, k = fit_rotation_scale(pdr, true)
    return {"heading_offset_deg": round(off, 2), "weinberg_k": round(k, 4), "until_t": t_cal}


# --------------------------------------------------------------------------- floor plan
#: plan variants a run can replay on: none; the store fronts and outline as walls only; walls
#: and the walkable area (the PF also kills particles outside it)
PLANS = ("none", "walls", "walkable")


def plan_body(data_dir: Path, variant: str, floor_info: dict, margin_m: float = 0.0) -> dict | None:
    """The ``PUT …/floors/0/plan`` body for a plan variant of ``geojson_map.json``: the
    competition's bbox transform onto the floor's width × height. ``walls``: the floor outline
    loses its ``type = floor`` mark, so every polygon's boundary is a wall and nothing is
    walkable space. ``margin_m`` ≠ 0 grows (or, negative, shrinks) the stores by that much:
    the plan is then taken into metres here and sent with the identity matrix."""
    if variant == "none":
        return None
    geojson = json.loads((Path(data_dir) / "geojson_map.json").read_text())
    if variant == "walls":
        for f in geojson["features"]:
            props = f.get("properties") or {}
            if props.get("type") == "floor":
                f["properties"] = {**props, "type": "outline"}
    elif variant != "walkable":
        raise CliError(f"unknown plan variant {variant!r} (one of {', '.join(PLANS)})", EXIT_USAGE)
    if margin_m:
        return {"geojson": _grown(geojson, floor_info, margin_m), "transform": {"matrix": [[1, 0, 0], [0, 1, 0]]}}
    return {"geojson": geojson, "transform": {"bbox": {"width_m": floor_info["width"], "height_m": floor_info["height"]}}}


def _grown(geojson: dict, floor_info: dict, margin_m: float) -> dict:
    """The plan in metres (bbox transform) with every polygon but the floor outline buffered by
    ``margin_m`` (mitred corners)."""
    import shapely
    from shapely.geometry import mapping, shape

    geoms = [shape(f["geometry"]) for f in geojson["features"]]
    x0, y0, x1, y1 = shapely.total_bounds(geoms)
    sx, sy = floor_info["width"] / (x1 - x0), floor_info["height"] / (y1 - y0)
    out = []
    for f, g in zip(geojson["features"], geoms, strict=True):
        g = shapely.transform(g, lambda xy: (xy - [x0, y0]) * [sx, sy])
        if (f.get("properties") or {}).get("type") != "floor" and g.geom_type in ("Polygon", "MultiPolygon"):
            g = g.buffer(margin_m, join_style="mitre")
            if g.is_empty:
                continue
        out.append({"type": "Feature", "properties": f.get("properties") or {}, "geometry": mapping(g)})
    return {"type": "FeatureCollection", "features": out}


# --------------------------------------------------------------------------- HTTP parts
async def _new_site(admin: LocalizerClient, name: str, floor_info: dict) -> dict:
    return await admin.create_site({"name": f"{name} {secrets.token_hex(3)}", "floors": [
        {"level": 0, "name": "F1", "width_m": floor_info.get("width"), "height_m": floor_info.get("height")}]})


def _map_rows(maps: list[Prepared], kinds: list[str]) -> list[dict]:
    rows = [r for p in maps for r in survey_rows(p.walk, p.scans, device=f"msft-{p.walk.name}")]
    rows = [{**r, "rss": {k: v for k, v in r["rss"].items() if k.split(":")[0] in kinds}} for r in rows]
    return [r for r in rows if r["rss"]]


async def _upload_and_train(admin: LocalizerClient, site_id, rows: list[dict], algorithm: str, params: dict | None,
                            kinds: list[str], chunk: int = 2000) -> tuple[int, dict]:
    accepted = 0
    for i in range(0, len(rows), chunk):
        accepted += (await admin.upload_survey(site_id, rows[i:i + chunk]))["accepted"]
    model = await admin.train_model(site_id, algorithm, params, kinds=kinds)
    model = await admin.wait_model(site_id, model["id"], timeout_s=600)
    if model.get("status") != "ready":
        raise CliError(f"training failed: {model.get('error')}")
    return accepted, model


async def map_cross_validation(admin: LocalizerClient, maps: list[Prepared], floor_info: dict, algorithm: str,
                               params: dict | None, kinds: list[str], folds: int = 4) -> dict:
    """Fingerprint error on *unseen walks* from the map walks alone: ``folds`` temporary
    sites, each trained without every ``folds``-th map walk, which is then located
    scan by scan. Returns the error summary and the ratio error / model sigma."""
    errors, sigmas = [], []
    for k in range(folds):
        held = [p for i, p in enumerate(maps) if i % folds == k]
        rest = [p for i, p in enumerate(maps) if i % folds != k]
        if not held or not rest:
            continue
        site = await _new_site(admin, f"msft cv {k}", floor_info)
        await _upload_and_train(admin, site["id"], _map_rows(rest, kinds), algorithm, params, kinds)
        for p in held:
            rows = await fingerprint_only(admin, site["id"], p)
            errors += [r["error_m"] for r in rows]
            sigmas += [r["sigma_m"] for r in rows]
        # The fold sites are kept: deleting the newest site lets SQLite hand its id (and
        # its models' ids) to the next one, and the server's per-process model cache,
        # keyed by model id, would then answer with the deleted model.
    e = np.asarray(errors)
    return {**summarise(e), "sigma_p50": round(float(np.median(sigmas)), 2) if sigmas else None}


async def build_map(admin: LocalizerClient, maps: list[Prepared], floor_info: dict, algorithm: str,
                    params: dict | None, kinds: list[str], site_name: str, fix_noise: str = "auto") -> dict:
    """Upload the map walks' scans as a survey (each fingerprint's ``device`` is its
    walk), train, wait.

    ``fix_noise="auto"``: a walk-wise cross-validation on the map walks
    (:func:`map_cross_validation`) measures how far a fix for an unseen walk is off;
    its median error ``e50`` sets ``cov_floor_m = e50 / 1.177`` (the σ of a Rayleigh
    distribution with that median) for the model that is trained. The fixes'
    covariances — the trackers' R — then say how good a fix for a new walk really
    is, instead of only the spread of its neighbours. ``"model"``: the model's own
    covariances. A number: that ``cov_floor_m``."""
    rows = _map_rows(maps, kinds)
    out: dict = {}
    params = dict(params or {})
    if fix_noise == "auto":
        cv = await map_cross_validation(admin, maps, floor_info, algorithm, params, kinds)
        out["cross_validation"] = cv
        if cv["p50"]:
            params["cov_floor_m"] = round(cv["p50"] / math.sqrt(2 * math.log(2)), 2)
    elif fix_noise != "model":
        params["cov_floor_m"] = float(fix_noise)
    site = await _new_site(admin, site_name, floor_info)
    accepted, model = await _upload_and_train(admin, site["id"], rows, algorithm, params or None, kinds)
    return {**out, "site_id": site["id"], "fingerprints": accepted, "model": model,
            "cov_floor_m": params.get("cov_floor_m")}


async def plan_site(admin: LocalizerClient, maps: list[Prepared], floor_info: dict, fmap: dict, opt: Options,
                    data_dir: Path, variant: str) -> int:
    """A second site with the same map (same rows, same model parameters, so the same fixes) and
    the floor plan ``variant`` imported onto its floor: sessions there run with the plan."""
    site = await _new_site(admin, f"msft site1 F1 plan {variant}", floor_info)
    params = dict(opt.params or {})
    if fmap.get("cov_floor_m") is not None:
        params["cov_floor_m"] = fmap["cov_floor_m"]
    await _upload_and_train(admin, site["id"], _map_rows(maps, list(opt.kinds)), opt.algorithm, params or None,
                            list(opt.kinds))
    body = plan_body(data_dir, variant, floor_info, opt.plan_margin_m)
    await admin.request("PUT", f"/api/v1/sites/{site['id']}/floors/0/plan", body)
    return site["id"]


async def fingerprint_only(device: LocalizerClient, site_id, p: Prepared) -> list[dict]:
    track = []
    for s in p.scans:
        if not p.walk.t_start <= s["t"] <= p.walk.t_end:
            continue
        try:
            fix = await device.locate(site_id, s["rss"])
        except ApiError as exc:
            if exc.status == 422:  # nothing in this scan is known to the model
                continue
            raise
        c = fix["covariance"]
        track.append((s["t"], fix["x"], fix["y"], c, math.sqrt(max(c[0][0] + c[1][1], 0.0) / 2)))
    rows = errors_against(p.walk, [r[:4] for r in track])
    sigma = {round(float(r[0]), 3): round(r[4], 2) for r in track}
    return [{**r, "sigma_m": sigma.get(r["t"])} for r in rows]


#: the filters whose sessions the server can smooth by their particles (``smoother=particles``)
PARTICLE_FILTERS = ("pf", "pf-xy")


def initial_direction_deg(waypoints: np.ndarray, min_m: float = 2.0) -> float:
    """The walk's true direction at its start: from the first waypoint to the first one at least
    ``min_m`` away (the last if none is; degrees clockwise from +y)."""
    d = waypoints[1:, 1:3] - waypoints[0, 1:3]
    far = np.flatnonzero(np.hypot(d[:, 0], d[:, 1]) >= min_m)
    dx, dy = d[far[0] if len(far) else -1]
    return math.degrees(math.atan2(dx, dy))


def first_step(w: Walk, steps: list[PdrStep]) -> PdrStep | None:
    """The walk's first step after its start (the first waypoint), None without one."""
    return next((s for s in steps if s.t > w.t_start), None)


def first_step_turn_deg(w: Walk, steps: list[PdrStep]) -> float:
    """How far the walk's true start direction is from its first step's reported heading (what a phone
    told its start direction learns of its own heading bias; 0 without a step)."""
    first = first_step(w, steps)
    return 0.0 if first is None else initial_direction_deg(w.waypoints) - first.heading_deg


async def track_session(device: LocalizerClient, site_id, p: Prepared, steps, flt: str, initial: bool,
                        interval_s: float, smoothed: bool = False, seed_salt: int | None = None,
                        filter_params: dict[str, float] | None = None, scans: bool = True,
                        heading_std_deg: float | None = None) -> dict:
    """Replay one walk through a session (``scans`` False: steps only, no fix reaches it). The
    session opens with the phone's own first heading (its compass: it tells the server nothing), or
    with ``heading_std_deg`` the walk's true start direction and that σ (``initial.heading_std_deg``)."""
    w = p.walk
    init = None
    if initial:
        init = {"x": float(w.waypoints[0, 1]), "y": float(w.waypoints[0, 2]), "floor": 0}
        first = first_step(w, steps)
        if heading_std_deg is not None:
            init |= {"heading_deg": round(initial_direction_deg(w.waypoints), 2), "heading_std_deg": heading_std_deg}
        elif first is not None:
            init["heading_deg"] = round(first.heading_deg, 2)
    seed = None if seed_salt is None else zlib.crc32(f"{w.name}|{seed_salt}".encode())
    session = await device.open_session(site_id, flt, init, seed=seed, filter_params=filter_params)
    batches = make_batches(steps, p.scans if scans else [], w.t_start, w.t_end, interval_s)
    batch_rows = []
    sent = refused = 0
    for b in batches:
        body = b.to_api()
        res = await device.post_batch(session["id"], body)
        e = res["estimate"]
        batch_rows.append((e["t"], e["x"], e["y"]))
        sent += len(body.get("scans") or [])
        refused += len(res.get("rejected_fixes") or [])
    track = await device.get_track(session["id"])
    after = await device.get_track(session["id"], smoothed=True) if smoothed else None
    # a PF session's own particles smoothed too (``smoother=particles``)
    particles = (await device.get_track(session["id"], smoothed=True, smoother="particles")
                 if smoothed and flt in PARTICLE_FILTERS else None)
    await device.close_session(session["id"])

    def scored(rows: list[dict]) -> list[dict]:
        return errors_against(w, [(e["t"], e["x"], e["y"], e["covariance"]) for e in rows
                                  if e.get("source") != "init"])

    return {"session_id": session["id"], "batches": len(batches), "track": scored(track),
            "smoothed": None if after is None else scored(after), "batch_estimates": errors_against(w, batch_rows),
            "particles": None if particles is None else scored(particles),
            "scans_sent": sent, "fixes_refused": refused}


@dataclass
class Options:
    filters: tuple[str, ...] = FILTERS
    algorithm: str = "knn"
    params: dict | None = None
    kinds: tuple[str, ...] = ("wifi",)
    calibration: str = "site"  # "site" | "first-segment" | "walk" (oracle) | "none"
    max_age_s: float = 3.0
    interval_s: float = 2.0
    initial: str = "yes"  # "yes" | "no" | "both"
    fix_noise: str = "auto"  # "auto" | "model" (see build_map)
    concurrency: int = 4
    #: the step noise the phone declares: "site" = the per-segment spread (bias included),
    #: "white" = the spread about each walk's own median (the bias left to the trackers),
    #: "none" = no std fields (the server's defaults, as a phone that declares nothing)
    step_noise: str = "site"
    #: the phones' heading filter (PdrConfig.heading): "gyro" (the gyro aligned once by the
    #: compass; chosen on folds 0–1, where it beat the others for every filter; on folds 2–3 it
    #: made the PF with the plan better and the rest worse, docs/client-sim.md) | "kalman" (gyro +
    #: magnetometer Kalman, the default before) | "quasi-static" (gyro; compass offset in
    #: undisturbed field only) | "qekf"
    heading: str = "gyro"
    #: False: the sessions get the steps only (what a tracker makes of its dead reckoning and the
    #: plan without a fix; a diagnostic — the map model's own calibration undoes any --fix-noise floor)
    session_scans: bool = True
    #: floor plan variants to replay every filter on (``PLANS``), and the stores' margin (m)
    plans: tuple[str, ...] = ("none",)
    plan_margin_m: float = 0.0
    #: also score each session's smoothed track (``GET …/track?smoothed=true``) as "<name> smoothed"
    smoothed: bool = False
    #: seed each session from its walk and this salt (the ``seed`` extension): runs of two settings
    #: with the same salt use the same draws walk by walk (None: the server's own seed per session)
    seed_salt: int | None = None
    #: tracker parameters per filter name (the ``filter_params`` extension), e.g. {"pf": {"q": 0.04}}
    filter_params: dict[str, dict[str, float]] | None = None
    #: sessions are told each walk's true start direction with this σ (degrees; ``initial.heading_std_deg``),
    #: and ``pdr-aligned`` scores the PDR turned by the same knowledge (None: neither)
    initial_heading_std: float | None = None


def walks_with_a_span(files: list[Path], role: str, progress=print) -> list[Walk]:
    """The walks of ``files`` with at least two waypoints: a walk with fewer has no time span to
    place its scans in or to score, and no segment to calibrate on; each left out is said."""
    walks = []
    for f in files:
        w = read_walk(f)
        if len(w.waypoints) < 2:
            progress(f"{role} walk {w.name} left out: {len(w.waypoints)} waypoint(s), at least 2 are needed")
        else:
            walks.append(w)
    if files and not walks:
        raise CliError(f"no {role} walk has two waypoints", EXIT_USAGE)
    return walks


async def run_msft(url: str, admin_key: str, device_key: str, data_dir: Path, map_files: list[Path],
                   test_files: list[Path], opt: Options, progress=print, transport=None) -> dict:
    ble = "ble" in opt.kinds
    map_walks = walks_with_a_span(map_files, "map", progress)
    pdr = pdr_config(opt.heading, map_walks)
    maps = [prepare(w, pdr, opt.max_age_s, ble) for w in map_walks]
    tests = [prepare(w, pdr, opt.max_age_s, ble) for w in walks_with_a_span(test_files, "test", progress)]
    site_cal = site_calibration(maps) | {"heading": pdr.heading, "field_ut": pdr.field_ut, "dip_deg": pdr.dip_deg}
    progress(f"site calibration from {site_cal['walks']} map walks ({pdr.heading} heading, field "
             f"{pdr.field_ut} µT, dip {pdr.dip_deg}°): heading offset "
             f"{site_cal['heading_offset_deg']}°, Weinberg k {site_cal['weinberg_k']}; declared step noise "
             + ("none (the server's defaults)" if opt.step_noise == "none" else
                f"{site_cal['length_std_m']} m, "
                f"{site_cal['heading_white_std_deg' if opt.step_noise == 'white' else 'heading_std_deg']}° ({opt.step_noise})"))
    floor_info = {}
    fi = Path(data_dir) / "floor_info.json"
    if fi.exists():
        floor_info = json.loads(fi.read_text()).get("map_info", {})

    kw = {"transport": transport} if transport else {}
    async with LocalizerClient(url, admin_key, **kw) as admin, LocalizerClient(url, device_key, **kw) as device:
        fmap = await build_map(admin, maps, floor_info, opt.algorithm, opt.params, list(opt.kinds),
                               f"msft site1 F1 ({len(maps)} map walks)", opt.fix_noise)
        m = fmap["model"]
        cv = fmap.get("cross_validation")
        if cv:
            progress(f"map cross-validation (unseen map walks): fingerprint error mean {cv['mean']} m, "
                     f"p50 {cv['p50']} m, p90 {cv['p90']} m; model sigma p50 {cv['sigma_p50']} m")
        progress(f"site {fmap['site_id']}: {fmap['fingerprints']} fingerprints; model {m['id']} {m['algorithm']} "
                 f"ready, cov_floor_m {fmap.get('cov_floor_m') or 'auto (model)'}")
        plan_sites = {"none": fmap["site_id"]}
        for variant in (v for v in opt.plans if v != "none"):
            plan_sites[variant] = await plan_site(admin, maps, floor_info, fmap, opt, Path(data_dir), variant)
            progress(f"site {plan_sites[variant]}: the map with the floor plan ({variant}, margin {opt.plan_margin_m} m)")
        sem = asyncio.Semaphore(opt.concurrency)
        sessions_ok = True

        async def one_walk(p: Prepared) -> dict:
            nonlocal sessions_ok
            w = p.walk
            if opt.calibration == "first-segment":
                cal = walk_calibration(p)
                eval_from = cal["until_t"]
            elif opt.calibration == "walk":  # oracle: the walk's own waypoints (a diagnostic)
                cal = walk_calibration(p, None)
                eval_from = w.t_start
            elif opt.calibration == "none":
                cal = {"heading_offset_deg": 0.0, "weinberg_k": 0.45}
                eval_from = w.t_start
            else:
                cal = {k: site_cal[k] for k in ("heading_offset_deg", "weinberg_k")}
                eval_from = w.t_start
            noise = {"length_std_m": None, "heading_std_deg": None} if opt.step_noise == "none" else {
                "length_std_m": site_cal["length_std_m"],
                "heading_std_deg": site_cal["heading_white_std_deg" if opt.step_noise == "white" else "heading_std_deg"]}
            steps = steps_from_events(p.events, cal["weinberg_k"], cal["heading_offset_deg"], **noise)
            methods: dict[str, list[dict]] = {}
            refused: dict[str, list[int]] = {}  # method: [fixes the gate refused, scans sent]
            async with sem:
                methods["pdr-only"] = errors_against(w, dead_reckon(steps, w.waypoints[0, 1:], w.t_start)[1:])
                if opt.initial_heading_std is not None:
                    turn = first_step_turn_deg(w, steps)
                    turned = [replace(s, heading_deg=s.heading_deg + turn) for s in steps]
                    methods["pdr-aligned"] = errors_against(w, dead_reckon(turned, w.waypoints[0, 1:], w.t_start)[1:])
                methods["fingerprint-only"] = await fingerprint_only(device, fmap["site_id"], p)
                variants = [(f, True, v) for v in opt.plans for f in opt.filters] if opt.initial in ("yes", "both") else []
                variants += [(f, False, v) for v in opt.plans for f in opt.filters] if opt.initial in ("no", "both") else []
                for flt, init, plan in variants:
                    if not sessions_ok:
                        break
                    name = (flt if init else f"{flt} (no initial)") + ("" if plan == "none" else f" [plan: {plan}]")
                    try:
                        res = await track_session(device, plan_sites[plan], p, steps, flt, init, opt.interval_s,
                                                  opt.smoothed, opt.seed_salt,
                                                  (opt.filter_params or {}).get(flt), opt.session_scans,
                                                  opt.initial_heading_std)
                    except ApiError as exc:
                        if exc.status in (404, 405) and "sessions" in str(exc):
                            sessions_ok = False
                            progress(f"tracking sessions unavailable on this server ({exc}); filters skipped")
                            break
                        raise
                    methods[name] = res["track"]
                    refused[name] = [res["fixes_refused"], res["scans_sent"]]
                    if res["smoothed"] is not None:
                        methods[f"{name} smoothed"] = res["smoothed"]
                    if res["particles"] is not None:
                        methods[f"{name} smoothed by particles"] = res["particles"]
            methods = {k: [r for r in v if r["t"] > eval_from] for k, v in methods.items()}
            n_steps = int(((p.events.t > w.t_start) & (p.events.t <= w.t_end)).sum())
            true_len = float(np.linalg.norm(np.diff(w.waypoints[:, 1:], axis=0), axis=1).sum())
            progress(f"{w.name}: {w.t_end - w.t_start:.0f} s, {true_len:.0f} m, {n_steps} steps, "
                     f"{len(p.scans)} scans; " + ", ".join(
                         f"{k} {summarise(r['error_m'] for r in v)['mean']}" for k, v in methods.items()))
            return {"walk": w.name, "duration_s": round(w.t_end - w.t_start, 1), "length_m": round(true_len, 1),
                    "steps": n_steps, "scans": len(p.scans), "calibration": cal, "eval_from_t": eval_from,
                    "methods": methods, "refused": refused}

        walks = await asyncio.gather(*(one_walk(p) for p in tests))

    table, per_walk = tabulate(walks)
    return {"data_dir": str(data_dir), "map_walks": [f.stem for f in map_files],
            "test_walks": [f.stem for f in test_files], "options": opt.__dict__ | {"filters": list(opt.filters),
                                                                                    "kinds": list(opt.kinds)},
            "site_calibration": site_cal, "map": fmap,
            "table": table, "per_walk_mean": per_walk, "walks": walks}


def tabulate(walks: list[dict]) -> tuple[dict, dict]:
    names = list(dict.fromkeys(k for w in walks for k in w["methods"]))
    table = {}
    for k in names:
        rows = [r for w in walks for r in w["methods"].get(k, [])]
        table[k] = summarise(r["error_m"] for r in rows) | consistency(rows)
        counts = [w["refused"][k] for w in walks if k in w.get("refused", {})]
        if counts and sum(c[1] for c in counts):
            table[k]["refused_pct"] = round(100.0 * sum(c[0] for c in counts) / sum(c[1] for c in counts), 1)
    per_walk = {w["walk"]: {k: summarise(r["error_m"] for r in v)["mean"] for k, v in w["methods"].items()}
                for w in walks}
    return table, per_walk


def combine_folds(results: list[dict], fold_ids: list[int] | None = None) -> dict:
    """One result from several folds: every walk is a test walk once (``fold_ids``: each
    result's fold number, default 0, 1, …)."""
    ids = fold_ids if fold_ids is not None else list(range(len(results)))
    walks = [w | {"fold": ids[i]} for i, r in enumerate(results) for w in r["walks"]]
    table, per_walk = tabulate(walks)
    return {"data_dir": results[0]["data_dir"], "folds": [{k: r[k] for k in (
        "map_walks", "test_walks", "site_calibration", "map")} for r in results],
            "test_walks": [w for r in results for w in r["test_walks"]], "options": results[0]["options"],
            "table": table, "per_walk_mean": per_walk, "walks": walks}


def markdown(result: dict) -> str:
    lines = ["| method | estimates | mean m | p50 m | p90 m | max m | NEES mean | NEES p50 | scans refused |",
             "|---|---|---|---|---|---|---|---|---|"]
    for k, s in sorted(result["table"].items(), key=lambda kv: (kv[1]["mean"] is None, kv[1]["mean"] or 0)):
        refused = f"{s['refused_pct']} %" if "refused_pct" in s else "—"
        lines.append(f"| {k} | {s['n']} | {s['mean']} | {s['p50']} | {s['p90']} | {s['max']} | "
                     f"{s.get('nees_mean', '—')} | {s.get('nees_p50', '—')} | {refused} |")
    names = list(result["table"])
    per = result["per_walk_mean"]
    lines += ["", f"Walks (of {len(per)}) where a method's mean error is below PDR alone / fingerprinting alone:", ""]
    for k in names:
        if k in ("pdr-only", "fingerprint-only"):
            continue
        vs = [sum(1 for row in per.values() if row.get(k) is not None and row.get(base) is not None
                  and row[k] < row[base]) for base in ("pdr-only", "fingerprint-only")]
        lines.append(f"- {k}: {vs[0]} / {vs[1]}")
    lines += ["", "Mean error per test walk (m):", "", "| walk | " + " | ".join(names) + " |",
              "|---|" + "---|" * len(names)]
    for walk, row in result["per_walk_mean"].items():
        lines.append(f"| {walk} | " + " | ".join(str(row.get(k, "")) for k in names) + " |")
    return "\n".join(lines) + "\n"


def filter_params_arg(text: str | None) -> dict[str, dict[str, float]] | None:
    """``--filter-params``: a JSON object of filter name → {parameter: number}."""
    if not text:
        return None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CliError(f"--filter-params is not JSON: {exc}", EXIT_USAGE) from None
    if not isinstance(value, dict) or not all(isinstance(v, dict) for v in value.values()):
        raise CliError('--filter-params must map filter names to objects, e.g. \'{"pf": {"q": 0.04}}\'', EXIT_USAGE)
    return value


def main(a) -> int:
    """``python -m client_sim msft``: start a server (fresh SQLite in a temp dir, generated
    keys) unless ``--url``, run the evaluation, print the table, write ``--out``."""
    import secrets
    import tempfile

    from .server_process import free_port, start_server, stop_server

    files = walk_files(a.data_dir)
    if not files:
        raise CliError(f"no walk files under {a.data_dir}", EXIT_USAGE)
    if a.folds:
        only = getattr(a, "only_folds", None)
        try:
            keep = list(range(a.folds)) if not only else [int(k) for k in only.split(",") if k.strip()]
        except ValueError:
            raise CliError(f"--only-folds {only!r}: a comma list of fold numbers", EXIT_USAGE) from None
        if not keep or any(not 0 <= k < a.folds for k in keep):
            raise CliError(f"--only-folds {only!r}: fold numbers from 0 to {a.folds - 1}", EXIT_USAGE)
        splits = [([f for i, f in enumerate(files) if i % a.folds != k], files[k::a.folds]) for k in keep]
    else:
        keep = None
        map_default, test_default = default_split(len(files), a.every)
        test_files = select_walks(files, a.test_walks, test_default)
        if a.map_walks:
            map_files = select_walks(files, a.map_walks, [])
        else:
            map_files = [f for f in files if f not in test_files]
        if set(map_files) & set(test_files):
            print("warning: some walks are both map and test walks", flush=True)
        splits = [(map_files, test_files)]
    opt = Options(filters=tuple(x for x in a.filters.split(",") if x), algorithm=a.algorithm,
                  params=json.loads(a.params) if a.params else None,
                  kinds=tuple(x for x in a.kinds.split(",") if x), calibration=a.calibration,
                  max_age_s=a.max_age, interval_s=a.interval, initial=a.initial, concurrency=a.concurrency,
                  fix_noise=a.fix_noise, step_noise=a.step_noise, session_scans=not a.no_session_scans,
                  heading=getattr(a, "heading", "gyro"),
                  plans=tuple(x for x in getattr(a, "plan", "none").split(",") if x),
                  plan_margin_m=float(getattr(a, "plan_margin", 0.0)), smoothed=bool(getattr(a, "smoothed", False)),
                  seed_salt=getattr(a, "seed_salt", None),
                  filter_params=filter_params_arg(getattr(a, "filter_params", None)),
                  initial_heading_std=getattr(a, "initial_heading_std", None))
    for variant in opt.plans:
        if variant not in PLANS:
            raise CliError(f"unknown --plan {variant!r} (comma list of {', '.join(PLANS)})", EXIT_USAGE)
    server, tmp = None, None
    url, admin_key, device_key = a.url, a.admin_key, a.device_key
    if not url:
        tmp = tempfile.TemporaryDirectory(prefix="msft-eval-")
        admin_key, device_key = f"msft-admin-{secrets.token_hex(6)}", f"msft-device-{secrets.token_hex(6)}"
        port = free_port()
        server = start_server(port, {"LOCALIZER_DATABASE_URL": f"sqlite:///{tmp.name}/msft.db",
                                     "LOCALIZER_ADMIN_KEYS": admin_key, "LOCALIZER_DEVICE_KEYS": device_key})
        url = f"http://127.0.0.1:{port}"
        print(f"server started at {url} (SQLite in {tmp.name})", flush=True)
    try:
        results = []
        for k, (map_files, test_files) in enumerate(splits):
            if len(splits) > 1:
                print(f"--- fold {k + 1}/{len(splits)}: {len(map_files)} map walks, {len(test_files)} test walks",
                      flush=True)
            results.append(asyncio.run(run_msft(url, admin_key, device_key, Path(a.data_dir), map_files, test_files,
                                                opt, progress=lambda s: print(s, flush=True))))
        result = results[0] if len(results) == 1 else combine_folds(results, keep)
    finally:
        if server is not None:
            stop_server(server)
        if tmp is not None:
            tmp.cleanup()
    md = markdown(result)
    print(md)
    if a.out:
        out = Path(a.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result | {"markdown": md}, indent=1))
        out.with_suffix(".md").write_text(md)
        print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0
