"""Nothing lost, nothing doubled under ``kill -9``: phones post batches while the server is killed.

    python benchmarks/kill9.py --seconds 60
    python benchmarks/kill9.py --seconds 60 --postgres postgresql://postgres@127.0.0.1:5432/postgres

Starts ``python -m server serve`` on 127.0.0.1 in its own process group, on a fresh SQLite
file (one process) or, with ``--postgres URL``, on a fresh database created beside the one
the URL names (two worker processes; dropped at the end). It creates a site and one session
per phone with an initial position; then ``--phones`` threads post batches of steps (plain
httpx, one batch at a time per phone, a batch that meets a connection error, a timeout or
a 503 is posted again with the same ``seq`` and body), while the main thread kills the
server's whole process group with SIGKILL every ``--kill-every`` seconds (±50 %) and
starts it again, for ``--seconds`` or ``--kills``, whichever comes first. Then every
phone finishes its batch in flight and the store is checked directly (SQL, no server):

- lost: a seq the phone posted with no stored answer, or a session whose ``last_seq`` is not
  its last posted seq;
- doubled: a seq with more track estimates than its steps, or a stored seq never posted;
- mismatched: a seq with fewer estimates than its steps, ``track_length`` not equal to the
  estimates stored, or an answer the phone got that differs from the stored one (rendered as
  the route renders it).

Exit status 1 if any count is not zero.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import create_engine, make_url, text

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from client_sim.server_process import free_port  # noqa: E402

ADMIN, DEVICE = "kill9-admin", "kill9-device"
API = "/api/v1"
STEPS = 3  # per batch


@dataclass
class Phone:
    session_id: str
    answers: dict[int, dict] = field(default_factory=dict)  # seq → the answer the phone got
    steps: dict[int, int] = field(default_factory=dict)  # seq → steps posted in it
    retries: int = 0
    errors: list[str] = field(default_factory=list)


class Server:
    """``python -m server serve`` in its own process group, killed with SIGKILL and restarted."""

    def __init__(self, env: dict[str, str], port: int, workers: int, log: Path):
        self.env, self.port, self.workers = {**os.environ, **env}, port, workers
        self.log = log.open("ab")  # the server's stderr, shown if it fails to start
        self.log_path = log
        self.process: subprocess.Popen | None = None

    def start(self, timeout_s: float = 120.0) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "server", "serve", "--port", str(self.port), "--workers", str(self.workers),
             "--log-level", "critical"],
            cwd=ROOT, env=self.env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=self.log,
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                tail = self.log_path.read_text(errors="replace")[-2000:]
                raise SystemExit(f"error: the server exited with code {self.process.returncode}:\n{tail}")
            try:
                if httpx.get(f"http://127.0.0.1:{self.port}/healthz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.kill()
        raise SystemExit(f"error: the server did not come up within {timeout_s:.0f} s")

    def kill(self) -> None:
        """SIGKILL to the server's process group (uvicorn's supervisor and its workers)."""
        if self.process is None:
            return
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.process.wait()
        deadline = time.monotonic() + 10  # the workers may outlive the supervisor by a moment
        while time.monotonic() < deadline:
            try:
                os.killpg(self.process.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        self.process = None


def post_batches(base: str, phone: Phone, index: int, stop: threading.Event) -> None:
    """Post batch after batch until ``stop``; each batch is posted until it gets an answer."""
    rng = random.Random(index)
    t, seq = 0.0, 0
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {DEVICE}"}, timeout=10) as http:
        while not stop.is_set():
            steps = []
            for _ in range(STEPS):
                t += 0.5
                steps.append({"t": t, "length_m": 0.7, "heading_deg": rng.uniform(0, 360)})
            body = {"seq": seq, "steps": steps}
            phone.steps[seq] = len(steps)
            while True:  # the same seq and body until it is answered
                try:
                    r = http.post(f"{API}/sessions/{phone.session_id}/batches", json=body)
                except httpx.TransportError:
                    phone.retries += 1
                    time.sleep(0.05)
                    continue
                if r.status_code == 503:
                    phone.retries += 1
                    time.sleep(0.05)
                    continue
                if r.status_code == 200:
                    phone.answers[seq] = r.json()
                else:
                    phone.errors.append(f"seq {seq}: {r.status_code} {r.text[:200]}")
                break
            seq += 1


def check_store(database_url: str, phones: list[Phone]) -> tuple[Counter, list[str]]:
    """Lost, doubled and mismatched batches, read from the store itself."""
    from server.api.sessions import batch_result
    from server.domain import BatchAnswer

    counts: Counter = Counter(lost=0, doubled=0, mismatched=0)
    notes: list[str] = []
    engine = create_engine(database_url)
    with engine.connect() as conn:
        for p in phones:
            sid = {"sid": p.session_id}
            last_seq, track_length = conn.execute(
                text("SELECT last_seq, track_length FROM tracking_sessions WHERE id = :sid"), sid).one()
            stored: dict[int, Any] = dict(
                conn.execute(text("SELECT seq, answer FROM session_batches WHERE session_id = :sid"), sid).all())
            per_seq: dict[int, int] = dict(conn.execute(text("SELECT seq, count(*) FROM track_estimates WHERE session_id = :sid "
                                             "AND seq IS NOT NULL GROUP BY seq"), sid).all())
            estimates = conn.execute(text("SELECT count(*) FROM track_estimates WHERE session_id = :sid"), sid).scalar()
            posted = sorted(p.steps)
            if posted and last_seq != posted[-1]:
                counts["lost"] += 1
                notes.append(f"{p.session_id}: last_seq {last_seq}, last posted {posted[-1]}")
            if track_length != estimates:
                counts["mismatched"] += 1
                notes.append(f"{p.session_id}: track_length {track_length}, {estimates} estimates stored")
            for seq in set(stored) - set(posted):
                counts["doubled"] += 1
                notes.append(f"{p.session_id} seq {seq}: stored, never posted")
            for seq in posted:
                if seq not in stored or seq not in p.answers:
                    counts["lost"] += 1
                    notes.append(f"{p.session_id} seq {seq}: {'not stored' if seq not in stored else 'never answered'}")
                    continue
                n = per_seq.get(seq, 0)
                if n > p.steps[seq]:
                    counts["doubled"] += 1
                    notes.append(f"{p.session_id} seq {seq}: {n} estimates for {p.steps[seq]} steps")
                elif n < p.steps[seq]:
                    counts["mismatched"] += 1
                    notes.append(f"{p.session_id} seq {seq}: {n} estimates for {p.steps[seq]} steps")
                raw = stored[seq]
                if isinstance(raw, str | bytes):  # a JSON column read through plain SQL
                    import orjson

                    raw = orjson.loads(raw)
                rendered = batch_result(BatchAnswer.from_dict(raw)).model_dump(mode="json")
                if rendered != p.answers[seq]:
                    counts["mismatched"] += 1
                    notes.append(f"{p.session_id} seq {seq}: the phone got another answer than the stored one")
    engine.dispose()
    return counts, notes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0, help="how long the phones post (bound)")
    parser.add_argument("--kills", type=int, default=1000, help="stop after this many kills (bound)")
    parser.add_argument("--kill-every", type=float, default=3.0, help="mean seconds between kills (±50 %%)")
    parser.add_argument("--phones", type=int, default=8)
    parser.add_argument("--filter", default="kf")
    parser.add_argument("--postgres", metavar="URL", help="run on a fresh database of this PostgreSQL server, 2 workers")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = random.Random(args.seed)

    tmp = tempfile.TemporaryDirectory(prefix="kill9-")
    admin_url = None
    if args.postgres:
        admin_url = make_url(args.postgres).set(drivername="postgresql+psycopg")
        db_name = f"kill9_{os.getpid()}"
        with create_engine(admin_url, isolation_level="AUTOCOMMIT").connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{db_name}"'))
        database_url = admin_url.set(database=db_name).render_as_string(hide_password=False)
        workers = 2
    else:
        database_url = f"sqlite:///{Path(tmp.name) / 'kill9.db'}"
        workers = 1
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = Server({"LOCALIZER_DATABASE_URL": database_url, "LOCALIZER_ADMIN_KEYS": ADMIN,
                     "LOCALIZER_DEVICE_KEYS": DEVICE, "LOCALIZER_EMBEDDED_WORKER": "false"}, port, workers,
                    Path(tmp.name) / "server.log")
    kills = 0
    try:
        server.start()
        with httpx.Client(base_url=base, timeout=30) as http:
            site = http.post(f"{API}/sites", json={"name": "kill9", "floors": [{"level": 0}]},
                             headers={"Authorization": f"Bearer {ADMIN}"}).json()
            phones = []
            for i in range(args.phones):
                r = http.post(f"{API}/sessions", headers={"Authorization": f"Bearer {DEVICE}"},
                              json={"site_id": site["id"], "filter": args.filter,
                                    "initial": {"x": 5.0 + i, "y": 5.0, "floor": 0}})
                r.raise_for_status()
                phones.append(Phone(r.json()["id"]))
        stop = threading.Event()
        threads = [threading.Thread(target=post_batches, args=(base, p, i, stop), daemon=True)
                   for i, p in enumerate(phones)]
        t0 = time.monotonic()
        for th in threads:
            th.start()
        down_s = 0.0
        while kills < args.kills:
            wait = args.kill_every * rng.uniform(0.5, 1.5)
            if time.monotonic() + wait - t0 >= args.seconds:
                break
            time.sleep(wait)
            server.kill()
            kills += 1
            t_down = time.monotonic()
            server.start()
            down_s += time.monotonic() - t_down
        time.sleep(max(0.0, args.seconds - (time.monotonic() - t0)))
        stop.set()
        for th in threads:
            th.join(timeout=120)
        elapsed = time.monotonic() - t0
        server.kill()  # the store is checked with no server running

        counts, notes = check_store(database_url, phones)
        posted = sum(len(p.steps) for p in phones)
        errors = [e for p in phones for e in p.errors]
        print(f"kill9 ({'PostgreSQL, 2 workers' if args.postgres else 'SQLite, 1 process'}, {args.phones} phones, "
              f"filter {args.filter}): {elapsed:.0f} s, down {down_s:.0f} s while restarting")
        print(f"batches posted: {posted}  kills: {kills}  retried posts: {sum(p.retries for p in phones)}  "
              f"other answers: {len(errors)}")
        print(f"lost: {counts['lost']}  doubled: {counts['doubled']}  mismatched: {counts['mismatched']}")
        for line in (errors + notes)[:20]:
            print("  " + line)
        return 1 if errors or any(counts.values()) else 0
    finally:
        server.kill()
        if admin_url is not None:
            with create_engine(admin_url, isolation_level="AUTOCOMMIT").connect() as conn:
                conn.execute(text(f'DROP DATABASE IF EXISTS "kill9_{os.getpid()}" WITH (FORCE)'))
        tmp.cleanup()


if __name__ == "__main__":
    sys.exit(main())
