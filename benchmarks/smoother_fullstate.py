"""The smoother over the whole self-calibrating state [x, y, b, s] (served) against smoothing the
position alone (what a track stored without states, or a seed form, gets).

    python benchmarks/smoother_fullstate.py --split heldout --n 16 --fixes both

Runs the held-out (or tune) scenarios of ``benchmarks/scenario_family.py`` in process, as the
server runs a session (a batch every 2 s, the state stored and loaded between batches, the
estimates' ``FullState`` kept as the server stores them with the track), and smooths each track
both ways with ``tracking.smoother.smooth_track``. Prints the live, position-only and whole-state
smoothed mean errors at the steps and their NEES (mean / median) per filter;
docs/msft-evaluation.md has the figures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import benchmarks.scenario_family as sf  # noqa: E402
from server.estimation.tracking.smoother import smooth_track  # noqa: E402


def run(name: str, w, fixes, site) -> dict[str, list[float]]:
    r = sf.replay(name, w, fixes, site)
    truth = {s.t: p for s, p in zip(w.steps, w.truth[1:], strict=True)}
    track, states = r.track, r.states
    answers = {"live": track, "position": smooth_track(track), "whole": smooth_track(track, None, states)}
    out: dict[str, list[float]] = {}
    for key, estimates in answers.items():
        for e in estimates:
            if e.source != "step":
                continue
            d = np.array([e.x, e.y]) - truth[e.t]
            out.setdefault(key, []).append(float(np.hypot(*d)))
            out.setdefault(f"nees_{key}", []).append(float(d @ np.linalg.solve(np.array(e.covariance), d)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=sorted(sf.RANGES), default="heldout")
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--fixes", choices=("wknn", "gaussian", "both"), default="both")
    ap.add_argument("--filters", default="ekf,ukf,skpf,pf")
    a = ap.parse_args()
    filters = a.filters.split(",")
    for kind in ("wknn", "gaussian") if a.fixes == "both" else (a.fixes,):
        sums: dict[str, dict[str, list[float]]] = {f: {} for f in filters}
        for i in range(a.n):
            sc = sf.draw(a.split, i)
            world = sf.World(sc)
            w = sf.walk(world)
            fixes: sf.GaussianFixes | sf.ModelFixes
            if kind == "gaussian":
                fixes, site = sf.GaussianFixes(w, sc.gauss_fix_std_m, sc.seed + 4), sf.SiteMap()
            else:
                fixes, site = sf.ModelFixes(world.model("wknn"), 1.0), world.site()
            for f in filters:
                for key, values in run(f, w, fixes, site).items():
                    sums[f].setdefault(key, []).extend(values)
        print(f"\n{a.split} scenarios 0-{a.n - 1}, {kind} fixes: mean error m at the steps (NEES mean / median)\n")
        print("| filter | live | smoothed, position only | smoothed, whole state (served) |")
        print("|---|---|---|---|")
        for f in filters:
            r = {k: np.array(v) for k, v in sums[f].items()}
            cells = [f"{r[k].mean():.3f} ({r['nees_' + k].mean():.2f} / {np.median(r['nees_' + k]):.2f})"
                     for k in ("live", "position", "whole")]
            print(f"| {f} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
