"""Micro-benchmark: µs per predict (step) and per update (fix) for every tracker.

Run from the repository root:  python benchmarks/tracker_cost.py [--repeat N]
Also prints the cost ratio PF-1000 / SKPF measured in the same process (the PF's default is
a fixed 1,000 particles), and the to_dict/from_dict cost and stored size (what a server pays
per batch to load and store a session). Every tracker runs on a floor with walls; ``pf, no plan``
is the PF without them, where each update also keeps the cloud's spread (``kalman_floor``). The steps'
headings are drawn at random, so no straight run forms; ``skpf, straight`` walks one way (heading
σ 2°), so its grid heading reference observes every 8 steps. Each figure is the best of
``--rounds`` rounds, the trackers' rounds interleaved, so the ratios hold on a shared machine.

Last, a whole batch as ``benchmarks/sessions_load.py`` posts it (2 steps and a scan whose beacons
give ranges, on its synthetic site without a plan but with its survey's grid, a fix near the walker
standing in for the model's) through ``SessionEstimator``: restored from its JSON state, applied,
stored again, as the server does per batch (its HTTP and database work aside), for ``pf`` and ``skpf``;
and the pf session smoothed by its particles as ``GET …/track?smoothed=true&smoother=particles``
serves it (every batch replayed from the inputs the session keeps), per batch and against a live batch.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.sessions_load import walk  # noqa: E402
from client_sim.errors import number  # noqa: E402
from server.estimation.replay import RecordedBatch, RecordingFixes, smoothed_by_replay  # noqa: E402
from server.estimation.session import SessionEstimator  # noqa: E402
from server.estimation.tracking import make_tracker, tracker_from_dict, tracker_names  # noqa: E402
from server.estimation.tracking.particle_smoother import DEFAULT_LAG  # noqa: E402
from server.estimation.types import Beacon, Estimate, Fix, Scan, SiteMap, Step, step_displacement  # noqa: E402
from tests.helpers.synthetic import make_site  # noqa: E402

WALLS = [[-50.0, y, 50.0, y] for y in (-20.0, 20.0)] + [[x, -50.0, x, 50.0] for x in (-30.0, 30.0)]


ROUNDS = 5


def best_us(fn, n: int) -> float:
    """Best of 3 runs of n calls, µs per call."""
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for i in range(n):
            fn(i)
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e6


class Bench:
    """One tracker's timed calls. ``run_round`` times each kind of call once (n calls, µs per
    call) and keeps the best round: every tracker's rounds are interleaved with the others'
    (``measure``), so load that comes and goes on the machine lands on all of them alike and the
    ratios between trackers hold even when the absolute figures move."""

    def __init__(self, name: str, repeat: int, walls=WALLS, straight: bool = False):
        rng = np.random.default_rng(0)
        headings = rng.normal(0.0, 2.0, repeat) if straight else rng.uniform(0, 360, repeat)
        self.steps = [Step(i, 0.7, float(h), 0.1, 5.0) for i, h in enumerate(headings)]
        self.fixes = [Fix(float(x), float(y), 0, np.eye(2) * 2.0) for x, y in rng.normal(0, 1, (repeat, 2))]
        self.tracker = make_tracker(name, [0.0, 0.0], np.eye(2), walls=walls, seed=0)
        self.repeat = repeat
        self.best = {"predict_us": float("inf"), "update_us": float("inf"), "store_load_us": float("inf")}

    def run_round(self) -> None:
        t = self.tracker
        calls = {
            "predict_us": (lambda i: t.predict(self.steps[i]), self.repeat),
            "update_us": (lambda i: t.update(self.fixes[i]), self.repeat),
            "store_load_us": (lambda i: tracker_from_dict(json.loads(json.dumps(t.to_dict()))),
                              max(self.repeat // 10, 10)),
        }
        for key, (fn, n) in calls.items():
            t0 = time.perf_counter()
            for i in range(n):
                fn(i)
            self.best[key] = min(self.best[key], (time.perf_counter() - t0) / n * 1e6)

    def result(self) -> dict[str, float]:
        return {**self.best, "state_bytes": len(json.dumps(self.tracker.to_dict()))}


class BatchBench:
    """A session's batches as ``sessions_load`` posts them, in-process (``run_round``: µs per batch,
    the best round kept, as ``Bench``). Each scan's fix is the walker's position (the steps summed,
    as ``walk`` moves it) plus N(0, 1.5² m²), declared as σ 2 m: what a fingerprint model of that
    site gives, without the model's cost (the same for every filter)."""

    def __init__(self, name: str, repeat: int):
        synth = make_site()
        self.site = SiteMap(beacons={t["id"]: Beacon(t["id"], t["x"], t["y"], t["floor"], t["tx_power_dbm"],
                                                     t["path_loss_exponent"]) for t in synth.transmitters},
                            grids={(0, 0): 0.0})  # (its survey's grid: reference points on a square grid)
        rng = np.random.default_rng(1)
        batches = walk(synth, 1)
        start = next(batches)
        xy = np.array([start["x"], start["y"]])
        self.batches: list[tuple[list[Step], list[Scan], Fix]] = []
        for _ in range(repeat):
            b = next(batches)
            steps = [Step(s["t"], s["length_m"], s["heading_deg"]) for s in b["steps"]]
            for s in steps:
                xy = xy + step_displacement(s.length_m, s.heading_deg)
            x, y = xy + rng.normal(0.0, 1.5, 2)
            fix = Fix(float(x), float(y), 0, np.eye(2) * 4.0)
            self.batches.append((steps, [Scan(c["t"], c["rss"]) for c in b["scans"]], fix))
        est = SessionEstimator(name, seed=0)
        init = est.start([start["x"], start["y"]], None, 0, [], None, "init")
        self.state = json.loads(json.dumps(est.to_dict()))
        self.best = float("inf")
        self._fix: Fix | None = None
        #: the last round's track and recorded batches (as the server keeps a pf session's), for ``replay_round``
        self.track: list[Estimate] = [replace(init, t=self.batches[0][0][0].t)]
        self.recorded: list[RecordedBatch] = []
        self.best_replay = float("inf")

    def fix(self, scan: Scan, near) -> Fix:  # (the ``FixSource``)
        assert self._fix is not None
        return self._fix

    def run_round(self) -> None:
        state = self.state
        track, recorded = self.track[:1], []
        t0 = time.perf_counter()
        for steps, scans, fix in self.batches:
            self._fix = fix
            est = SessionEstimator.from_dict(state)
            recording = RecordingFixes(self)
            track += est.apply_batch(steps, scans, recording, self.site).estimates
            recorded.append(recording.batch(steps, scans))
            state = json.loads(json.dumps(est.to_dict()))
        self.best = min(self.best, (time.perf_counter() - t0) / len(self.batches) * 1e6)
        self.track, self.recorded = track, recorded

    def replay_round(self) -> None:
        """The whole session smoothed by its particles as ``smoother=particles`` serves it (µs per batch)."""
        t0 = time.perf_counter()
        if smoothed_by_replay(self.state, self.recorded, self.site, self.track) is None:
            raise RuntimeError("the replay did not reproduce the track")
        self.best_replay = min(self.best_replay, (time.perf_counter() - t0) / len(self.batches) * 1e6)


def measure(benches: dict[str, Bench], rounds: int = ROUNDS) -> dict[str, dict[str, float]]:
    """Each tracker's best of ``rounds``, the rounds interleaved across trackers."""
    for _ in range(rounds):
        for b in benches.values():
            b.run_round()
    return {name: b.result() for name, b in benches.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=number(int, 1), default=500)
    parser.add_argument("--rounds", type=number(int, 1), default=ROUNDS, help="rounds, interleaved across trackers (best kept)")
    args = parser.parse_args()
    benches = {name: Bench(name, args.repeat) for name in tracker_names()}
    benches["pf, no plan"] = Bench("pf", args.repeat, walls=None)
    benches["skpf, straight"] = Bench("skpf", args.repeat, straight=True)
    results = measure(benches, args.rounds)
    print(f"{'tracker':12s} {'predict µs':>12s} {'update µs':>12s} {'store+load µs':>14s} {'state bytes':>12s}")
    for name, r in results.items():
        print(f"{name:12s} {r['predict_us']:12.1f} {r['update_us']:12.1f} {r['store_load_us']:14.1f} "
              f"{r['state_bytes']:12d}")
    for pf_name, sk_name in (("pf", "skpf"), ("pf", "skpf, straight"), ("pf, no plan", "skpf"), ("pf-xy", "skpf-xy")):
        pf, sk = results[pf_name], results[sk_name]
        print(
            f"{pf_name} (1,000 particles) / {sk_name} cost ratio: predict {pf['predict_us'] / sk['predict_us']:.1f}x, "
            f"update {pf['update_us'] / sk['update_us']:.1f}x, "
            f"step+update {(pf['predict_us'] + pf['update_us']) / (sk['predict_us'] + sk['update_us']):.1f}x"
        )
    batch = {name: BatchBench(name, max(args.repeat // 5, 20)) for name in ("pf", "skpf")}
    for _ in range(args.rounds):
        for b in batch.values():
            b.run_round()
        batch["pf"].replay_round()
    pf_batch = batch["pf"]
    print(f"a sessions_load batch (2 steps + 1 scan, state restored and stored through JSON): "
          f"pf {pf_batch.best:.0f} µs, skpf {batch['skpf'].best:.0f} µs, ratio {pf_batch.best / batch['skpf'].best:.1f}x")
    print(f"the pf session smoothed by its particles (smoother=particles: replayed from its kept inputs, lag "
          f"{DEFAULT_LAG}): {pf_batch.best_replay:.0f} µs per batch, {pf_batch.best_replay / pf_batch.best:.2f}x a live batch")


if __name__ == "__main__":
    main()
