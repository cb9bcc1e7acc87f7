"""PDR noise levels measured on real walks: where the self-calibrating trackers' defaults come from.

    python benchmarks/pdr_noise.py ../shared/data/msft_site1_f1 [--walks even|odd|all] [--heading kalman|gyro|quasi-static]

The project's on-phone PDR (``client_sim.pdr``: peak detector, Weinberg length, gyro +
magnetometer Kalman heading; ``--heading gyro`` for the gyro aligned once by the compass,
``--heading quasi-static`` for the gyro heading whose compass offset is corrected in
undisturbed field only, with the site field of these walks) runs on
each walk's raw IMU; the site calibration (one
heading offset and one Weinberg k for the site, the median of per-walk fits, as
``client_sim msft`` ships them) is applied. Each step inside a waypoint segment of at
least 3 m is compared with that segment (the path between waypoints is close to straight):

- heading residual e_k = PDR heading − segment direction; per walk its circular median is
  the walk's **heading bias** (its spread over walks → ``BIAS0_STD_DEG``); the residual
  minus a running median over 9 steps is the **white heading noise** (→ the default
  ``heading_std_deg``); the running median's change over 20 steps gives the **bias
  random walk** per step, σ² = var(Δ₂₀)/20 (→ ``BIAS_WALK_DEG``);
- per segment, PDR length / true length; per walk the median is the walk's **step
  scale** (its spread → ``SCALE0_STD``); the in-walk spread of segment ratios, times the
  median step length and √(steps per segment), is the **white length noise** (→ the
  default ``length_std_m``).

By default the walks with an even index are used (the same walks are then *not* used to
report the MSFT figures as held out: see the README's "Tracking design").
"""

from __future__ import annotations

import argparse
import math
import sys
from itertools import pairwise
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from client_sim.msft import detect_steps, fit_rotation_scale, read_walk, segment_displacements  # noqa: E402
from client_sim.msft_eval import pdr_config  # noqa: E402
from client_sim.pdr.step_length import weinberg  # noqa: E402


def robust_std(x) -> float:
    x = np.asarray(x, float)
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def wrap(deg):
    return (np.asarray(deg, float) + 180.0) % 360.0 - 180.0


def running_median(x: np.ndarray, half: int = 4) -> np.ndarray:
    return np.array([np.median(x[max(0, i - half): i + half + 1]) for i in range(len(x))])


def measure(paths: list[Path], min_segment_m: float = 3.0, heading: str = "kalman") -> dict:
    walks = [(p.name, read_walk(p)) for p in paths]
    cfg = pdr_config(heading, [w for _, w in walks])
    events = [(name, w, detect_steps(w, cfg)) for name, w in walks]
    offsets, ks = [], []
    for _, w, ev in events:
        pdr, true = segment_displacements(ev, w.waypoints, 1.0)
        if len(pdr) and np.linalg.norm(true, axis=1).sum() > 5.0:
            off, k = fit_rotation_scale(pdr, true)
            offsets.append(off)
            ks.append(k)
    a = np.radians(offsets)
    off = math.degrees(math.atan2(np.median(np.sin(a)), np.median(np.cos(a))))
    k = float(np.median(ks))
    biases, white, walk_var, scales, len_white, steps_all = [], [], [], [], [], []
    for _, w, ev in events:
        lengths = weinberg(ev.swing, np.zeros_like(ev.swing), k)
        res, ratios, seg_n = [], [], []
        for (t0, x0, y0), (t1, x1, y1) in pairwise(w.waypoints):
            dist = math.hypot(x1 - x0, y1 - y0)
            m = (ev.t > t0) & (ev.t <= t1)
            if dist < min_segment_m or m.sum() < 2:
                continue
            true_h = math.degrees(math.atan2(x1 - x0, y1 - y0))
            res.extend(wrap(ev.heading_deg[m] + off - true_h).tolist())
            ratios.append(float(lengths[m].sum()) / dist)
            seg_n.append(int(m.sum()))
        if len(res) < 20:
            continue
        r = np.asarray(res)
        b = math.degrees(math.atan2(np.median(np.sin(np.radians(r))), np.median(np.cos(np.radians(r)))))
        biases.append(b)
        local = running_median(r)
        white.extend((r - local).tolist())
        if len(local) > 40:
            d20 = local[20:] - local[:-20]
            walk_var.append(float(np.median(d20**2)) / 0.455 / 20.0)  # median of χ²₁ is 0.455
        scales.append(float(np.median(ratios)))
        rr = np.asarray(ratios) / np.median(ratios) - 1.0
        len_white.extend((rr * np.sqrt(seg_n)).tolist())
        steps_all.extend(lengths.tolist())
    step_m = float(np.median(steps_all))
    return {
        "walks": len(biases),
        "site_heading_offset_deg": round(off, 2),
        "weinberg_k": round(k, 4),
        "median_step_m": round(step_m, 3),
        "heading_bias_std_deg": round(robust_std(biases), 2),
        "heading_bias_abs_p90_deg": round(float(np.percentile(np.abs(biases), 90)), 2),
        "heading_white_std_deg": round(robust_std(white), 2),
        "bias_walk_deg_per_step": round(math.sqrt(float(np.median(walk_var))), 3) if walk_var else None,
        "scale_std": round(robust_std(scales), 3),
        "length_white_std_m": round(robust_std(len_white) * step_m, 3),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--walks", default="even", help="even | odd | all (indices into the sorted walk files)")
    ap.add_argument("--heading", default="kalman", help="kalman | gyro | quasi-static | qekf (PdrConfig.heading)")
    a = ap.parse_args()
    files = sorted((a.data_dir / "path_data_files").glob("*.txt"))
    if a.walks == "even":
        files = files[::2]
    elif a.walks == "odd":
        files = files[1::2]
    for k, v in measure(files, heading=a.heading).items():
        print(f"{k:28s} {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
