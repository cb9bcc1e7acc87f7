"""Prototype, not served: an RTS smoother over the whole self-calibrating state [x, y, b, s]
against the served one, which smooths the position marginal of the stored track.

    python benchmarks/smoother_fullstate.py --split heldout --n 16 --fixes both

Runs the held-out (or tune) scenarios of ``benchmarks/scenario_family.py`` in process, as the
server runs a session (a batch every 2 s, the state stored and loaded between batches), and
records each step's filtered state and covariance before the prediction and the predicted ones
after it (the trackers' ``predict`` wrapped here; the server stores none of this). The full-state
recursion uses the step's Jacobian F (``selfcal.jacobians`` at the filtered state):

    C_k = P_{k|k} Fᵀ P_{k+1|k}⁻¹,  x_{k|N} = x_{k|k} + C_k (x_{k+1|N} − x_{k+1|k}),
    P_{k|N} = P_{k|k} + C_k (P_{k+1|N} − P_{k+1|k}) C_kᵀ,

so a heading bias learned late bends the path before it as the bias, not as independent noise
per step. Prints, at each step, the live, served (position-marginal) and full-state smoothed
mean errors and NEES (mean / median) per filter. docs/msft-evaluation.md has the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import benchmarks.scenario_family as sf  # noqa: E402
from server.estimation.session import SessionEstimator  # noqa: E402
from server.estimation.tracking import EKFTracker, ParticleFilterTracker, SKPFTracker, UKFTracker, selfcal  # noqa: E402
from server.estimation.tracking.smoother import smooth_track  # noqa: E402
from server.estimation.types import Step  # noqa: E402

#: (step, (x, P) before its prediction, (x, P) after it) for the session being run
RECORD: list[tuple[Step, tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]] = []


def _recording(cls) -> None:
    predict = cls.predict

    def recorded(self, step: Step) -> None:
        before = (self.state_mean.copy(), self.state_covariance.copy())
        predict(self, step)
        RECORD.append((step, before, (self.state_mean.copy(), self.state_covariance.copy())))

    cls.predict = recorded


def full_state_rts(record, final: tuple[np.ndarray, np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Smoothed states and covariances at times 0..n (time t: after the t-th step and its fixes)."""
    n = len(record)
    xf = [r[1][0] for r in record] + [final[0]]
    Pf = [r[1][1] for r in record] + [final[1]]
    xs, Ps = list(xf), list(Pf)
    for t in range(n - 1, -1, -1):
        step, _, (xp, Pp) = record[t]
        F, _ = selfcal.jacobians(xf[t], step.length_m, math.radians(step.heading_deg))
        C = Pf[t] @ F.T @ np.linalg.inv(Pp + 1e-9 * np.eye(4))
        xs[t] = xf[t] + C @ (xs[t + 1] - xp)
        Ps[t] = Pf[t] + C @ (Ps[t + 1] - Pp) @ C.T
    return xs, Ps


def run(name: str, w, fixes, site, batch_s: float = 2.0) -> dict[str, list[float]]:
    RECORD.clear()
    est = SessionEstimator(name, seed=7)
    est.start(w.truth[0], None, 0, [], None, "init")
    steps, scans = list(w.steps), list(w.scans)
    truth = {s.t: p for s, p in zip(w.steps, w.truth[1:], strict=True)}
    track = []
    t_end = batch_s
    while steps or scans:
        bs, bc = [s for s in steps if s.t < t_end], [s for s in scans if s.t < t_end]
        steps, scans = steps[len(bs):], scans[len(bc):]
        est = SessionEstimator.from_dict(json.loads(json.dumps(est.to_dict())))
        track += est.apply_batch(bs, bc, fixes, site).estimates
        t_end += batch_s
    assert est.tracker is not None
    xs, Ps = full_state_rts(list(RECORD), (est.tracker.state_mean.copy(), est.tracker.state_covariance.copy()))
    live = {e.t: e for e in track if e.source == "step"}
    served = {o.t: e for e, o in zip(smooth_track(track), track, strict=True) if o.source == "step"}
    out: dict[str, list[float]] = {k: [] for k in ("live", "served", "full", "nees_served", "nees_full")}
    for k, (step, _, _) in enumerate(RECORD):
        tr = truth[step.t]
        out["live"].append(math.hypot(live[step.t].x - tr[0], live[step.t].y - tr[1]))
        d_served = np.array([served[step.t].x, served[step.t].y]) - tr
        d_full = xs[k + 1][:2] - tr
        out["served"].append(float(np.hypot(*d_served)))
        out["full"].append(float(np.hypot(*d_full)))
        out["nees_served"].append(float(d_served @ np.linalg.solve(np.array(served[step.t].covariance), d_served)))
        out["nees_full"].append(float(d_full @ np.linalg.solve(Ps[k + 1][:2, :2] + 1e-9 * np.eye(2), d_full)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=sorted(sf.RANGES), default="heldout")
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--fixes", choices=("wknn", "gaussian", "both"), default="both")
    ap.add_argument("--filters", default="ekf,ukf,skpf,pf")
    a = ap.parse_args()
    for cls in (EKFTracker, UKFTracker, SKPFTracker, ParticleFilterTracker):
        _recording(cls)
    filters = a.filters.split(",")
    for kind in ("wknn", "gaussian") if a.fixes == "both" else (a.fixes,):
        sums: dict[str, dict[str, list[float]]] = {f: {} for f in filters}
        for i in range(a.n):
            sc = sf.draw(a.split, i)
            world = sf.World(sc)
            w = sf.walk(world)
            if kind == "gaussian":
                fixes, site = sf.GaussianFixes(w, sc.gauss_fix_std_m, sc.seed + 4), sf.SiteMap()
            else:
                fixes, site = sf.ModelFixes(world.model("wknn"), 1.0), world.site()
            for f in filters:
                for key, values in run(f, w, fixes, site).items():
                    sums[f].setdefault(key, []).extend(values)
        print(f"\n{a.split} scenarios 0-{a.n - 1}, {kind} fixes: mean error m at the steps (NEES mean / median)\n")
        print("| filter | live | smoothed, served (position marginal) | smoothed, full state |")
        print("|---|---|---|---|")
        for f in filters:
            r = {k: np.array(v) for k, v in sums[f].items()}
            print(f"| {f} | {r['live'].mean():.3f} | {r['served'].mean():.3f} ({r['nees_served'].mean():.2f} / "
                  f"{np.median(r['nees_served']):.2f}) | {r['full'].mean():.3f} ({r['nees_full'].mean():.2f} / "
                  f"{np.median(r['nees_full']):.2f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
