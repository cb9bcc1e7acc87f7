"""Error tables and plots from ``track`` results files.

Per (scenario, filter): mean, std, p50, p90 and max of the position error (m) over
the estimates of the sessions' tracks (falling back to the per-batch estimates), plus
the local PDR-only baseline. Writes ``errors.json``, ``errors.md``, ``cdf.png`` and
``trajectory.png``.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .world import get_world  # noqa: E402


def collect_errors(results: list[dict]) -> dict[tuple[str, str], list[float]]:
    """(scenario, filter) → all position errors; PDR-only appears as filter ``pdr-only``."""
    errs: dict[tuple[str, str], list[float]] = defaultdict(list)
    for res in results:
        for phone in res.get("phones", []):
            rows = phone.get("track") or phone.get("batch_estimates") or []
            errs[(res["scenario"], phone["filter"])] += [r["error_m"] for r in rows]
            errs[(res["scenario"], "pdr-only")] += [r["error_m"] for r in phone.get("pdr_only", [])]
    return errs


def stats(errors: list[float]) -> dict[str, float]:
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return {"n": 0}
    return {"n": int(e.size), "mean": float(e.mean()), "std": float(e.std()), "p50": float(np.percentile(e, 50)),
            "p90": float(np.percentile(e, 90)), "max": float(e.max())}


def markdown_table(table: dict[str, dict[str, dict]]) -> str:
    lines = ["| scenario | filter | n | mean (m) | std | p50 | p90 | max |", "|---|---|---|---|---|---|---|---|"]
    for scenario, by_filter in table.items():
        for flt, s in by_filter.items():
            if s["n"]:
                lines.append(f"| {scenario} | {flt} | {s['n']} | {s['mean']:.2f} | {s['std']:.2f} | "
                             f"{s['p50']:.2f} | {s['p90']:.2f} | {s['max']:.2f} |")
    return "\n".join(lines) + "\n"


def plot_cdf(errs: dict[tuple[str, str], list[float]], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 4))
    for (scenario, flt), e in sorted(errs.items()):
        if e:
            x = np.sort(e)
            ax.plot(x, np.arange(1, len(x) + 1) / len(x), label=f"{scenario} / {flt}")
    ax.set_xlabel("position error (m)")
    ax.set_ylabel("CDF")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_floor(ax, world, level: int = 0) -> None:
    for x1, y1, x2, y2 in world.floor(level).walls:
        ax.plot([x1, x2], [y1, y2], color="0.3", lw=1.5)
    for tx in world.transmitters:
        if tx.floor == level:
            ax.plot(tx.x, tx.y, "^" if tx.kind == "wifi" else "s", color="tab:red" if tx.kind == "wifi" else "tab:blue",
                    ms=5)
    ax.set_aspect("equal")


def plot_trajectories(results: list[dict], path: Path) -> None:
    """The first phone of each (scenario, filter): truth, server estimates, PDR-only."""
    seen, panels = set(), []
    for res in results:
        for phone in res.get("phones", []):
            key = (res["scenario"], phone["filter"])
            if key not in seen and (phone.get("track") or phone.get("batch_estimates")):
                seen.add(key)
                panels.append((res["scenario"], phone))
    n = max(1, len(panels))
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 4), squeeze=False)
    for ax, (scenario, phone) in zip(axes[0], panels, strict=False):  # one empty axis when no panel
        try:
            plot_floor(ax, get_world(scenario), int(phone["truth"]["floor"][0]))
        except (KeyError, FileNotFoundError, OSError):
            pass
        xy = np.array(phone["truth"]["xy"])
        ax.plot(xy[:, 0], xy[:, 1], "k-", lw=1, label="truth")
        est = phone.get("track") or phone.get("batch_estimates")
        ax.plot([e["x"] for e in est], [e["y"] for e in est], ".-", ms=2, lw=0.6, label=phone["filter"])
        pdr = phone.get("pdr_only", [])
        ax.plot([e["x"] for e in pdr], [e["y"] for e in pdr], "--", lw=0.8, label="PDR only")
        ax.set_title(f"{scenario} / {phone['filter']}", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_report(result_files: list[str | Path], out_dir: str | Path) -> dict:
    """Read track results files, write the tables and plots, return the numbers."""
    results = [json.loads(Path(p).read_text()) for p in result_files]
    results = [r for r in results if r.get("kind") == "track"]
    errs = collect_errors(results)
    table: dict[str, dict[str, dict]] = defaultdict(dict)
    for (scenario, flt), e in sorted(errs.items()):
        table[scenario][flt] = stats(e)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "errors.json").write_text(json.dumps({"table": table, "errors": {f"{s}/{f}": e for (s, f), e in errs.items()}}))
    (out / "errors.md").write_text(markdown_table(table))
    plot_cdf(errs, out / "cdf.png")
    plot_trajectories(results, out / "trajectory.png")
    return dict(table)


def plot_scenario(world, path: str | Path, seed: int = 0) -> None:
    """Floor plan(s) of a world with transmitters, reference points and one simulated walk."""
    from .phone import simulate_phone

    levels = [f.level for f in world.floors]
    fig, axes = plt.subplots(1, len(levels), figsize=(5 * len(levels), 4), squeeze=False)
    trace = simulate_phone(world, world.routes[0], seed)
    dr = trace.dead_reckoning()
    for ax, level in zip(axes[0], levels, strict=True):
        plot_floor(ax, world, level)
        rps = np.array([p[:2] for p in world.reference_points if p[2] == level] or np.empty((0, 2)))
        if len(rps):
            ax.plot(rps[:, 0], rps[:, 1], ".", color="0.6", ms=3, label="reference points")
        on = trace.walk.floor == level
        ax.plot(trace.walk.xy[on, 0], trace.walk.xy[on, 1], "k.", ms=2, label="true steps")
        if level == trace.walk.floor[0]:
            ax.plot(dr[:, 1], dr[:, 2], "g--", lw=0.8, label="on-phone PDR")
        ax.set_title(f"{world.name}, floor {level}", fontsize=9)
    axes[0][0].legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
