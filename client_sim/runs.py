"""The three client runs: survey a site, track phones, crowdsource a map.

Each is an ``async def`` taking the server URL and keys, so tests and the CLI call
the same code. Results are plain dicts, JSON-serialisable, consumed by
:mod:`client_sim.report`.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Iterable
from typing import Any

import httpx
import numpy as np
from tqdm import tqdm

from .consistency import squared_mahalanobis
from .http_client import LocalizerClient
from .phone import PhoneTrace, simulate_phone
from .radio import RadioModel
from .walker import route_variant
from .world import World, get_world

SURVEY_HEADINGS = (0.0, 90.0, 180.0, 270.0)


def _world(scenario: World | str) -> World:
    return scenario if isinstance(scenario, World) else get_world(scenario)


# ------------------------------------------------------------------ survey


def survey_fingerprints(world: World, scans_per_heading: int = 5, seed: int = 0,
                        kinds: Iterable[str] = ("wifi", "ble")) -> list[dict]:
    """Fingerprints of a survey: at every reference point, N scans facing each of four headings.

    A fingerprint holds one WiFi and one BLE scan taken together; the label ``rpNNN``
    ties a reference point's fingerprints together.
    """
    rng = np.random.default_rng([world.seed, seed, 0x5E])
    radio = RadioModel(world)
    out, t = [], 0.0
    for i, (x, y, floor) in enumerate(world.reference_points):
        for heading in SURVEY_HEADINGS:
            for _ in range(scans_per_heading):
                rss: dict[str, float] = {}
                for kind in kinds:
                    rss.update(radio.scan(x, y, floor, heading, kind, rng))
                t += 1.0
                if rss:
                    out.append({"x": x, "y": y, "floor": floor, "rss": rss, "heading_deg": heading,
                                "t": t, "device": "client_sim", "label": f"rp{i:03d}"})
    return out


async def run_survey(base_url: str, admin_key: str, scenario: World | str, *, scans_per_heading: int = 5,
                     seed: int = 0, train: str | None = None, site_name: str | None = None, site_id: int | None = None,
                     chunk: int = 2000, wait_model_s: float = 300.0, transport: httpx.AsyncBaseTransport | None = None,
                     progress: bool = False) -> dict:
    """Create the scenario's site (or use ``site_id``), upload its survey, optionally train a model
    (and wait for it)."""
    world = _world(scenario)
    fps = survey_fingerprints(world, scans_per_heading, seed)
    async with LocalizerClient(base_url, admin_key, transport=transport, key_name="admin key") as api:
        if site_id is None:
            site_id = (await api.create_site(world.site_payload(site_name)))["id"]
        else:
            await api.get_site(site_id)  # 404 before any upload
        accepted = 0
        for start in tqdm(range(0, len(fps), chunk), desc="survey upload", disable=not progress):
            accepted += (await api.upload_survey(site_id, fps[start:start + chunk]))["accepted"]
        result: dict[str, Any] = {"site_id": site_id, "scenario": world.name, "fingerprints": len(fps),
                                  "accepted": accepted, "reference_points": len(world.reference_points)}
        if train:
            model = await api.train_model(site_id, train)
            result["model"] = await api.wait_model(site_id, model["id"], wait_model_s)
    return result


# ------------------------------------------------------------------ track


def _estimate_row(est: dict, trace: PhoneTrace) -> dict:
    """An estimate against the truth: its error and, when it has a covariance, its NEES."""
    tx, ty, tf = trace.truth_at(est["t"])
    row = {"t": est["t"], "x": est["x"], "y": est["y"], "floor": est["floor"], "source": est.get("source"),
           "true_x": round(tx, 3), "true_y": round(ty, 3), "true_floor": tf,
           "error_m": round(math.hypot(est["x"] - tx, est["y"] - ty), 3)}
    if est.get("covariance") is not None:
        row["nees"] = round(squared_mahalanobis(est["x"] - tx, est["y"] - ty, est["covariance"]), 3)
    return row


async def track_phone(api: LocalizerClient, site_id, trace: PhoneTrace, filter: str, *, initial: bool = True,
                      interval_s: float = 2.0, speed: float = 0.0, retries: int = 4, on_batch=None,
                      session_seed: int | None = None) -> dict:
    """One phone's session: open, post every batch (retrying with the same seq), read the track.
    ``session_seed`` (the sessions' ``seed`` extension) fixes the tracker's draws; None: the server's."""
    walk = trace.walk
    init = None
    if initial:
        init = {"x": float(walk.xy[0, 0]), "y": float(walk.xy[0, 1]), "floor": int(walk.floor[0]),
                "heading_deg": float(walk.heading_deg[0])}
    session = await api.open_session(site_id, filter, init, seed=session_seed)
    rows, failures = [], 0
    started = time.monotonic()
    for batch in trace.batches(interval_s):
        if speed > 0:  # pace batches like a phone in real time (scaled)
            due = (batch.seq + 1) * interval_s / speed
            await asyncio.sleep(max(0.0, due - (time.monotonic() - started)))
        try:
            res = await api.post_batch(session["id"], batch.to_api(), retries)
            rows.append(_estimate_row(res["estimate"], trace))
        except Exception:  # noqa: BLE001 - one phone's failure is recorded, not fatal
            failures += 1
        if on_batch:
            on_batch()
    track = []
    try:
        track = [_estimate_row(e, trace) for e in await api.get_track(session["id"])]
        await api.close_session(session["id"])
    except Exception:  # noqa: BLE001
        failures += 1
    dr = trace.dead_reckoning()
    pdr_rows = [_estimate_row({"t": float(t), "x": float(x), "y": float(y), "floor": int(walk.floor[0])}, trace)
                for t, x, y in dr]
    return {"session_id": session["id"], "filter": filter, "batch_estimates": rows, "track": track,
            "pdr_only": pdr_rows, "failed_posts": failures, "steps_true": walk.n_steps,
            "steps_detected": len(trace.steps), "scans": len(trace.scans)}


def plan_phones(world: World, phones: int, filters: list[str], seed: int, wifi_hz: float, ble_hz: float,
                random_routes: bool = False) -> list[tuple[int, str, int, PhoneTrace]]:
    """(phone index, filter, route index, trace) for each phone; filters assigned round-robin."""
    radio = RadioModel(world)
    plans = []
    for i in range(phones):
        rng = np.random.default_rng([seed, i, 0x7A])
        if random_routes:
            route = route_variant(world.routes, rng)
            r_idx = -1
        else:
            r_idx = i % len(world.routes)
            route = world.routes[r_idx]
        trace = simulate_phone(world, route, seed * 100_003 + i, wifi_hz=wifi_hz, ble_hz=ble_hz, radio=radio)
        plans.append((i, filters[i % len(filters)], r_idx, trace))
    return plans


def session_seed(run_seed: int, phone: int) -> int:
    """A phone's session seed (``0..2³²−1``) from the run's seed and its index."""
    return int(np.random.SeedSequence([run_seed, phone, 0x5E55]).generate_state(1)[0])


async def run_track(base_url: str, device_key: str, scenario: World | str, site_id, *, phones: int = 4,
                    filters: list[str] | tuple[str, ...] = ("skpf",), seed: int = 0, interval_s: float = 2.0,
                    speed: float = 0.0, wifi_hz: float = 1.0, ble_hz: float = 2.0, initial: bool = True,
                    retries: int = 4, transport: httpx.AsyncBaseTransport | None = None,
                    progress: bool = False) -> dict:
    """K phones walk the scenario's routes concurrently, each in its own session, seeded from ``seed``
    and the phone (``session_seed``): a run repeats to the digit, a particle filter's draws included."""
    world = _world(scenario)
    plans = plan_phones(world, phones, list(filters), seed, wifi_hz, ble_hz)
    n_batches = sum(len(p[3].batches(interval_s)) for p in plans)
    bar = tqdm(total=n_batches, desc="batches", disable=not progress)
    async with LocalizerClient(base_url, device_key, transport=transport, key_name="device key") as api:
        async def one(i, flt, r_idx, trace):
            try:
                res = await track_phone(api, site_id, trace, flt, initial=initial, interval_s=interval_s,
                                        speed=speed, retries=retries, on_batch=bar.update,
                                        session_seed=session_seed(seed, i))
            except Exception as exc:  # noqa: BLE001 - e.g. the session could not be opened
                res = {"filter": flt, "error": str(exc), "batch_estimates": [], "track": [], "pdr_only": []}
            return dict(res, phone=i, route=r_idx, truth=trace.walk.to_dict())

        out = await asyncio.gather(*(one(*p) for p in plans))
    bar.close()
    return {"kind": "track", "scenario": world.name, "site_id": site_id, "seed": seed, "initial": initial,
            "interval_s": interval_s, "phones": out}


# ------------------------------------------------------------------ crowd


async def probe_locate(api: LocalizerClient, world: World, site_id, n: int, seed: int) -> dict:
    """Cold-start accuracy: ``locate`` fresh scans at ``n`` random reference points; with the NIS of
    each answer against the truth under its own covariance (``nis_mean``/``nis_p50``: 2 / 1.39 when the
    served covariance is honest)."""
    rng = np.random.default_rng([world.seed, seed, 0xC0])
    radio = RadioModel(world)
    errors, nis, floor_hits, failures = [], [], 0, 0
    for k in rng.choice(len(world.reference_points), size=min(n, len(world.reference_points)), replace=False):
        x, y, floor = world.reference_points[k]
        heading = float(rng.choice([0.0, 90.0, 180.0, 270.0]))
        rss = {**radio.scan(x, y, floor, heading, "wifi", rng), **radio.scan(x, y, floor, heading, "ble", rng)}
        try:
            fix = await api.locate(site_id, rss, heading)
        except Exception:  # noqa: BLE001 - 409 before any model is ready
            failures += 1
            continue
        errors.append(math.hypot(fix["x"] - x, fix["y"] - y))
        nis.append(squared_mahalanobis(fix["x"] - x, fix["y"] - y, fix["covariance"]))
        floor_hits += int(fix["floor"] == floor)
    return {"probes": n, "answered": len(errors), "failed": failures,
            "mean_error_m": float(np.mean(errors)) if errors else None,
            "nis_mean": float(np.mean(nis)) if nis else None, "nis_p50": float(np.median(nis)) if nis else None,
            "floor_hit_rate": floor_hits / len(errors) if errors else None}


async def run_crowd(base_url: str, admin_key: str, device_key: str, scenario: World | str, *, rounds: int = 3,
                    phones: int = 10, filter: str = "skpf", seed: int = 0, train: str | None = "knn",
                    probes: int = 20, site_id=None, interval_s: float = 2.0, wifi_hz: float = 1.0,
                    ble_hz: float = 2.0, transport: httpx.AsyncBaseTransport | None = None,
                    progress: bool = False) -> dict:
    """Phones without a survey walk (sessions without ``initial``) in rounds; after each round
    a model is trained on what the server crowdsourced, and cold-start fixes are probed."""
    world = _world(scenario)
    async with LocalizerClient(base_url, admin_key, transport=transport, key_name="admin key") as admin, \
            LocalizerClient(base_url, device_key, transport=transport, key_name="device key") as device:
        if site_id is None:
            site_id = (await admin.create_site(world.site_payload(f"{world.name}-crowd-{seed}")))["id"]
        await admin.update_site_settings(site_id, {"crowdsourcing": True})
        # No survey: the first fixes come from the path-loss model of the transmitters' known positions.
        bootstrap = await admin.wait_model(site_id, (await admin.train_model(site_id, "propagation"))["id"])
        out_rounds = [{"round": -1, "model": bootstrap, "site": await admin.get_site(site_id),
                       "locate": await probe_locate(device, world, site_id, probes, seed * 1000 + 999)}]
        for r in tqdm(range(rounds), desc="crowd rounds", disable=not progress):
            plans = plan_phones(world, phones, [filter], seed * 1000 + r, wifi_hz, ble_hz, random_routes=True)
            results = await asyncio.gather(*(
                track_phone(device, site_id, trace, flt, initial=False, interval_s=interval_s,
                            session_seed=session_seed(seed * 1000 + r, i))
                for i, flt, _, trace in plans), return_exceptions=True)
            walked = [x for x in results if isinstance(x, dict)]
            entry: dict[str, Any] = {"round": r, "phones": phones, "sessions_ok": len(walked),
                                     "session_errors": [str(x) for x in results if not isinstance(x, dict)][:3]}
            errs = [e["error_m"] for res in walked for e in res["batch_estimates"]]
            entry["tracking_mean_error_m"] = float(np.mean(errs)) if errs else None
            nees = [e["nees"] for res in walked for e in res["batch_estimates"] if "nees" in e]
            entry["tracking_nees_mean"] = float(np.mean(nees)) if nees else None
            entry["tracking_nees_p50"] = float(np.median(nees)) if nees else None
            entry["tracking_floor_hit_rate"] = (float(np.mean([e["floor"] == e["true_floor"] for res in walked
                                                               for e in res["batch_estimates"]])) if errs else None)
            if train:
                try:
                    model = await admin.train_model(site_id, train)
                    model = await admin.wait_model(site_id, model["id"])
                    if model.get("status") == "ready" and not model.get("active"):
                        model = await admin.activate_model(site_id, model["id"])
                    entry["model"] = model
                except Exception as exc:  # noqa: BLE001 - e.g. nothing crowdsourced yet
                    entry["model_error"] = str(exc)
            entry["site"] = await admin.get_site(site_id)
            entry["locate"] = await probe_locate(device, world, site_id, probes, seed * 1000 + r)
            out_rounds.append(entry)
    return {"kind": "crowd", "scenario": world.name, "site_id": site_id, "seed": seed, "rounds": out_rounds}
