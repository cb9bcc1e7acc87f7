"""Many phones feeding tracking sessions at once, against a real server process.

    python benchmarks/sessions_load.py --phones 200 --seconds 30
    python benchmarks/sessions_load.py --phones 1000 --seconds 60 --workers 2
    python benchmarks/sessions_load.py --phones 300 --seconds 20 --workers 2 \
        --database-url postgresql+psycopg://postgres@127.0.0.1/loadbench

Starts ``python -m server serve`` on a fresh SQLite file (or ``--database-url``, which may
be used again: each run's site has a name of its own), creates a synthetic site (survey +
a trained knn model), opens one session per phone with a start position, then every phone
posts one batch per second (2 steps + 1 RSS scan) for ``--seconds``, phones staggered over
the first second. A post that fails at the
transport level is retried with the same ``seq`` (the server answers a replay from its
store). Prints the batch latency percentiles and the achieved rate, then checks the
stored data: every session has exactly one stored answer per posted seq and exactly
3 track estimates per batch (+1 initial) — no lost and no doubled batches.

First, closed loop from the same client: the server's capacity for batches, and the
baseline, its capacity for its cheapest database-backed request (``GET /healthz``), the two
in turn for ``--rounds`` rounds (default 3; the medians are printed with their range); the
ratio says how close batches come to what this machine's HTTP stack can carry at all
and, unlike either figure, hardly moves with whatever else the machine is doing. The CPU
time per batch (the server's processes, and on PostgreSQL the database's too) gives the
figure per core: how many phones at one batch a second one core carries.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import aiohttp
import httpx
import numpy as np
from sqlalchemy import create_engine, text

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.http_load import client, closed_loop, cpu_seconds, database_cpu_seconds  # noqa: E402
from client_sim.errors import number  # noqa: E402
from client_sim.server_process import start_server, stop_server  # noqa: E402
from server.auth import create_key  # noqa: E402
from server.db import Database  # noqa: E402
from tests.helpers.synthetic import make_site  # noqa: E402

ADMIN, DEVICE = "bench-admin", "bench-device"
API = "/api/v1"


def prepare_site(base: str, synth) -> int:
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {ADMIN}"}, timeout=120) as c:
        site = c.post(f"{API}/sites", json={"name": f"bench {time.time_ns()}", "floors": [{"level": 0}, {"level": 1}],
                                            "transmitters": synth.transmitters}).json()
        rows = synth.survey(scans_per_rp=6, seed=1).to_rows()
        for row in rows:
            row.pop("building", None)
        assert c.post(f"{API}/sites/{site['id']}/surveys", json={"fingerprints": rows}).status_code == 201
        model = c.post(f"{API}/sites/{site['id']}/models", json={"algorithm": "knn", "params": {"k": 3}}).json()
        deadline = time.monotonic() + 300
        while model["status"] not in ("ready", "failed") and time.monotonic() < deadline:
            time.sleep(0.2)
            model = c.get(f"{API}/sites/{site['id']}/models/{model['id']}").json()
        if model["status"] != "ready":
            raise SystemExit(f"model did not train: {model}")
        return site["id"]


def walk(synth, i: int):
    """Phone ``i``'s start and then its batches, one a second: 2 steps of 0.7 m and a scan."""
    rng = np.random.default_rng(i)
    x, y = float(rng.uniform(0, 12)), float(rng.uniform(0, 8))
    heading = float(rng.uniform(0, 360))
    yield {"x": x, "y": y, "floor": 0}
    t, seq = 0.0, 0
    while True:
        steps = []
        for _ in range(2):
            t += 0.5
            if not (0 <= x + 0.7 * math.sin(math.radians(heading)) <= 12 and 0 <= y + 0.7 * math.cos(math.radians(heading)) <= 8):
                heading = (heading + 180) % 360
            x += 0.7 * math.sin(math.radians(heading))
            y += 0.7 * math.cos(math.radians(heading))
            steps.append({"t": t, "length_m": 0.7, "heading_deg": heading})
        yield {"seq": seq, "steps": steps, "scans": [{"t": t + 0.01, "rss": synth.scan(x, y, 0, None, rng, 2.0)}]}
        seq += 1


async def open_session(http: aiohttp.ClientSession, site_id: int, filter: str, initial: dict) -> str:
    async with http.post(f"{API}/sessions", json={"site_id": site_id, "filter": filter, "initial": initial}) as r:
        r.raise_for_status()
        return (await r.json())["id"]


async def phone(http: aiohttp.ClientSession, site_id: int, synth, i: int, seconds: int, filter: str,
                start_at: float, latencies: list[float], failures: list[str]) -> tuple[str, int]:
    """Posts one batch a second from ``start_at``; a failed post is retried with the same seq."""
    batches = walk(synth, 10_000 + i)
    sid = await open_session(http, site_id, filter, next(batches))
    loop = asyncio.get_running_loop()
    ok = 0
    for seq in range(seconds):
        body = next(batches)
        await asyncio.sleep(max(0.0, start_at + seq - loop.time()))
        for attempt in range(5):
            started = loop.time()
            try:
                async with http.post(f"{API}/sessions/{sid}/batches", json=body) as r:
                    text = await r.text()
            except (TimeoutError, aiohttp.ClientError) as exc:
                failures.append(f"{sid} seq {seq}: retry after {type(exc).__name__}")
                await asyncio.sleep(0.2 * (attempt + 1))
                continue
            if r.status == 200:
                latencies.append(loop.time() - started)
                ok += 1
                break
            failures.append(f"{sid} seq {seq}: {r.status} {text[:200]}")
            if r.status < 500:
                break
            await asyncio.sleep(0.2 * (attempt + 1))
    return sid, ok


@dataclass(frozen=True)
class Round:
    """One round of the closed-loop capacity measurement."""

    healthz_per_s: float
    batches_per_s: float
    #: server CPU ms per request (healthz, batch); None where /proc is not readable
    cpu_ms: tuple[float, float] | None
    #: PostgreSQL's CPU ms per batch (None on SQLite or without /proc)
    db_cpu_ms: float | None

    @property
    def ratio(self) -> float:
        return self.batches_per_s / self.healthz_per_s


async def capacities(base: str, server_pid: int, site_id: int, synth, filter: str, device_key: str,
                     rounds: int = 3, requests: int = 3000, concurrency: int = 64) -> tuple[list[Round], list]:
    """Closed loop, same client and concurrency, ``rounds`` times in turn: ``GET /healthz`` (one
    ``SELECT 1``), then batches from ``concurrency`` phones each posting its next batch once the
    last is answered (the same sessions go on from round to round). Each with the server's CPU
    time per request. Alternating the two in rounds puts load that comes and goes on the machine
    on both alike; the spread over rounds says how far one figure can be trusted."""
    out: list[Round] = []
    async with client(base, device_key, concurrency) as http:
        await closed_loop(http, lambda i: ("GET", "/healthz", None), 200, concurrency)  # warm up
        walks = [walk(synth, i) for i in range(concurrency)]
        sessions = [await open_session(http, site_id, filter, next(w)) for w in walks]
        per_phone = requests // concurrency
        n = per_phone * concurrency

        async def post_all(sid: str, batches) -> None:
            for _ in range(per_phone):
                async with http.post(f"{API}/sessions/{sid}/batches", json=next(batches)) as r:
                    await r.read()
                    r.raise_for_status()

        for _ in range(rounds):
            cpu0 = cpu_seconds(server_pid)
            elapsed, _ = await closed_loop(http, lambda i: ("GET", "/healthz", None), requests, concurrency)
            cpu1, db1 = cpu_seconds(server_pid), database_cpu_seconds()  # healthz's end is the batches' start
            began = time.perf_counter()
            await asyncio.gather(*(post_all(sid, w) for sid, w in zip(sessions, walks, strict=True)))
            batches_per_s = n / (time.perf_counter() - began)
            cpu2, db2 = cpu_seconds(server_pid), database_cpu_seconds()
            cpu_ms = None
            if cpu0 is not None and cpu1 is not None and cpu2 is not None:
                cpu_ms = ((cpu1 - cpu0) / requests * 1e3, (cpu2 - cpu1) / n * 1e3)
            db_ms = None if db1 is None or db2 is None else (db2 - db1) / n * 1e3
            out.append(Round(requests / elapsed, batches_per_s, cpu_ms, db_ms))
    return out, [(sid, per_phone * rounds) for sid in sessions]


async def run(base: str, site_id: int, synth, phones: int, seconds: int, filter: str, device_key: str):
    async with client(base, device_key, phones) as http:
        loop = asyncio.get_running_loop()
        t0 = loop.time() + 2.0
        latencies: list[float] = []
        failures: list[str] = []
        began = time.perf_counter() + 2.0  # when the first batch is due
        sessions = await asyncio.gather(*[
            phone(http, site_id, synth, i, seconds, filter, t0 + i / phones, latencies, failures)
            for i in range(phones)
        ])
        elapsed = time.perf_counter() - began
    return sessions, latencies, failures, elapsed


def check_store(database_url: str, sessions: list[tuple[str, int]]) -> list[str]:
    """Exactly one stored answer per batch answered 200 and 3 estimates per batch (+1 initial)."""
    engine = create_engine(database_url)
    problems = []
    with engine.connect() as conn:
        answers: dict[str, int] = dict(conn.execute(text(
            "SELECT session_id, count(*) FROM session_batches GROUP BY session_id")).all())
        estimates: dict[str, int] = dict(conn.execute(text(
            "SELECT session_id, count(*) FROM track_estimates GROUP BY session_id")).all())
        last: dict[str, int] = dict(conn.execute(text("SELECT id, last_seq FROM tracking_sessions")).all())
    engine.dispose()
    for sid, n in sessions:
        if answers.get(sid, 0) != n or estimates.get(sid, 0) != 1 + 3 * n:
            problems.append(f"{sid}: {answers.get(sid, 0)} answers, {estimates.get(sid, 0)} estimates, "
                            f"last_seq {last.get(sid)} for {n} batches answered 200")
    return problems


def _spread(values: list[float], fmt: str) -> str:
    """The median, and the range over rounds when there are several."""
    med = format(float(np.median(values)), fmt)
    return med if len(values) == 1 else f"{med} (rounds {format(min(values), fmt)}–{format(max(values), fmt)})"


def print_capacity(rounds: list[Round], on_postgres: bool) -> None:
    """The closed-loop figures: medians over the rounds, with their range."""
    print(f"capacity, closed loop, 64 phones, {len(rounds)} round(s): "
          f"{_spread([r.batches_per_s for r in rounds], '.0f')} batches/s; baseline GET /healthz from the same "
          f"client: {_spread([r.healthz_per_s for r in rounds], '.0f')} requests/s; "
          f"ratio {_spread([r.ratio for r in rounds], '.2f')}")
    cpu = [r.cpu_ms for r in rounds if r.cpu_ms is not None]
    if not cpu:
        return
    healthz_ms, batch_ms = [c[0] for c in cpu], [c[1] for c in cpu]
    print(f"server CPU per request: batch {_spread(batch_ms, '.2f')} ms, healthz {_spread(healthz_ms, '.2f')} ms; "
          f"ratio {_spread([b / h for b, h in zip(batch_ms, healthz_ms, strict=True)], '.2f')}")
    db = [r.db_cpu_ms for r in rounds if r.db_cpu_ms is not None] if on_postgres else [0.0]  # SQLite's CPU is the server's
    if on_postgres and db:
        print(f"PostgreSQL CPU per batch: {_spread(db, '.2f')} ms (every postgres process on this machine)")
    if db:
        total = float(np.median(batch_ms)) + float(np.median(db))
        print(f"per core: {1000.0 / total:.0f} phones at one batch a second (server + database CPU "
              f"{total:.2f} ms per batch, medians); 1,000 phones need {total:.1f} cores")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--phones", type=number(int, 1), default=200)
    parser.add_argument("--seconds", type=number(int, 1), default=30, help="batches per phone (one a second)")
    parser.add_argument("--filter", default="skpf")
    parser.add_argument("--workers", type=number(int, 1), default=1, help="server processes")
    parser.add_argument("--database-url", help="default: a new SQLite file")
    parser.add_argument("--port", type=number(int, 1, high=65535), default=8793)
    parser.add_argument("--rounds", type=number(int, 1), default=3,
                        help="closed-loop capacity rounds, healthz and batches in turn (the median is the figure)")
    parser.add_argument("--stored-key", action="store_true",
                        help="phones use a key created as `python -m server keys create` makes one (looked up in "
                             "the database on every request) instead of one from LOCALIZER_DEVICE_KEYS")
    args = parser.parse_args()

    synth = make_site(nx=4, ny=3, spacing_m=4.0, floors=(0, 1), seed=2)
    with tempfile.TemporaryDirectory() as tmp:
        url = args.database_url or f"sqlite:///{Path(tmp) / 'bench.db'}"
        server = start_server(args.port, {"LOCALIZER_DATABASE_URL": url, "LOCALIZER_ADMIN_KEYS": ADMIN,
                                          "LOCALIZER_DEVICE_KEYS": DEVICE}, args.workers)
        try:
            base = f"http://127.0.0.1:{args.port}"
            site_id = prepare_site(base, synth)
            device_key = DEVICE
            if args.stored_key:
                db = Database(url)
                device_key = create_key(db, "bench phones", "device")[1]
                db.dispose()
            rounds, cap_sessions = asyncio.run(
                capacities(base, server.pid, site_id, synth, args.filter, device_key, max(1, args.rounds)))
            sessions, lat, failures, elapsed = asyncio.run(
                run(base, site_id, synth, args.phones, args.seconds, args.filter, device_key))
        finally:
            stop_server(server)
        lat_ms = np.array(lat) * 1000
        n = len(lat_ms)
        print_capacity(rounds, url.startswith("postgresql"))
        print(f"{args.phones} phones x {args.seconds} batches ({args.filter}, {args.workers} worker(s), "
              f"{url.split(':')[0]}{', stored key' if args.stored_key else ''}): "
              f"{n} batches answered in {elapsed:.1f} s = {n / elapsed:.0f} batches/s "
              f"(offered {args.phones}/s)")
        if n:
            print(f"batch latency ms: p50 {np.percentile(lat_ms, 50):.1f}  p90 {np.percentile(lat_ms, 90):.1f}  "
                  f"p99 {np.percentile(lat_ms, 99):.1f}  max {lat_ms.max():.1f}")
        print(f"failed or retried posts: {len(failures)}")
        for f in failures[:5]:
            print("  ", f)
        problems = check_store(url, sessions + cap_sessions)
        print(f"stored data: {'OK, no lost or doubled batches' if not problems else f'{len(problems)} sessions wrong'}")
        for p in problems[:5]:
            print("  ", p)
        if problems:
            raise SystemExit(1)


if __name__ == "__main__":
    main()
