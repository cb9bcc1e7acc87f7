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
from matplotlib.lines import Line2D  # noqa: E402

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


def track_table(results: list[dict]) -> dict[str, dict[str, dict]]:
    """scenario → filter → error statistics, from ``track`` results."""
    table: dict[str, dict[str, dict]] = defaultdict(dict)
    for (scenario, flt), e in sorted(collect_errors(results).items()):
        table[scenario][flt] = stats(e)
    return dict(table)


def crowd_table(result: dict) -> str:
    """Markdown table of a ``crowd`` run, one row per round (``bootstrap``: the propagation model)."""
    def num(v, fmt: str = "{:.2f}") -> str:
        return "—" if v is None else fmt.format(v)

    lines = ["| round | model | crowd fingerprints | sessions ok | tracking mean (m) | locate answered | locate mean (m) |",
             "|---|---|---|---|---|---|---|"]
    for r in result["rounds"]:
        m = r.get("model")
        model = f"{m['id']} {m['algorithm']} {m['status']}" if m else f"none ({r.get('model_error', '')})"[:60]
        loc = r.get("locate") or {}
        cells = ["bootstrap" if r["round"] < 0 else str(r["round"]), model,
                 num(r.get("site", {}).get("fingerprints", {}).get("crowd"), "{}"),
                 f"{r['sessions_ok']}/{r['phones']}" if "sessions_ok" in r else "—",
                 num(r.get("tracking_mean_error_m")), f"{loc.get('answered', 0)}/{loc.get('probes', 0)}",
                 num(loc.get("mean_error_m"))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_cdf(errs: dict[tuple[str, str], list[float]], path: Path) -> None:
    """One CDF line per (scenario, filter), best mean first in the legend; PDR-only dashed."""
    curves = sorted(((float(np.mean(e)), key, np.sort(e)) for key, e in errs.items() if e), key=lambda c: c[0])
    scenarios = {s for _, (s, _), _ in curves}
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for mean, (scenario, flt), x in curves:
        name = flt if len(scenarios) == 1 else f"{scenario} / {flt}"
        ax.step(x, np.arange(1, len(x) + 1) / len(x), where="post", lw=1.6 if flt != "pdr-only" else 1.2,
                ls="--" if flt == "pdr-only" else "-", color="k" if flt == "pdr-only" else None,
                label=f"{name} (mean {mean:.2f} m)")
    for q in (0.5, 0.9):
        ax.axhline(q, color="0.6", lw=0.7, ls=":")
        ax.annotate(f"p{int(q * 100)}", (1.0, q), xycoords=("axes fraction", "data"), xytext=(3, 0),
                    textcoords="offset points", va="center", fontsize=8, color="0.4")
    ax.set_xlim(left=0)
    ax.set_ylim(0, 1)
    ax.set_xlabel("position error (m)")
    ax.set_ylabel("fraction of estimates with error ≤ x")
    ax.set_title("Position error CDF" + (f" — {next(iter(scenarios))}" if len(scenarios) == 1 else ""))
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize=8, loc="lower right", title="method (best mean first)", title_fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_floor(ax, world, level: int = 0) -> None:
    """Walls, WiFi APs (red triangles) and iBeacons (blue squares) of one floor, axes in metres."""
    for x1, y1, x2, y2 in world.floor(level).walls:
        ax.plot([x1, x2], [y1, y2], color="0.65", lw=2.5, solid_capstyle="butt")
    for tx in world.transmitters:
        if tx.floor == level:
            ax.plot(tx.x, tx.y, TX_STYLE[tx.kind], ms=5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


TX_STYLE = {"wifi": "r^", "ble": "bs"}
LEGEND = [  # every marker and line kind of the trajectory plot
    Line2D([], [], color="0.65", lw=2.5, label="wall"),
    Line2D([], [], color="r", marker="^", ls="", label="WiFi access point"),
    Line2D([], [], color="b", marker="s", ls="", label="iBeacon"),
    Line2D([], [], color="k", lw=1.2, label="true walk"),
    Line2D([], [], color="k", marker="o", ls="", mfc="none", label="start"),
    Line2D([], [], color="tab:orange", marker=".", lw=0.8, label="server estimates (panel's filter)"),
    Line2D([], [], color="tab:green", ls="--", lw=1, label="PDR only (the phone's dead reckoning)"),
]


def plot_trajectories(results: list[dict], path: Path, columns: int = 3) -> None:
    """The first phone of each (scenario, filter), one panel each in a grid: truth, server
    estimates, PDR-only, on the floor plan; one legend for the whole figure."""
    seen, panels = set(), []
    for res in results:
        for phone in res.get("phones", []):
            key = (res["scenario"], phone["filter"])
            if key not in seen and (phone.get("track") or phone.get("batch_estimates")):
                seen.add(key)
                panels.append((res["scenario"], phone))
    cols = max(1, min(columns, len(panels)))
    rows = max(1, -(-len(panels) // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 4.0 * rows + 0.8), squeeze=False, layout="constrained")
    for ax in axes.flat[len(panels):]:
        ax.set_axis_off()
    for ax, (scenario, phone) in zip(axes.flat, panels, strict=False):
        try:
            plot_floor(ax, get_world(scenario), int(phone["truth"]["floor"][0]))
        except (KeyError, FileNotFoundError, OSError):
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
        xy = np.array(phone["truth"]["xy"])
        ax.plot(xy[:, 0], xy[:, 1], "k-", lw=1.2)
        ax.plot(xy[0, 0], xy[0, 1], "ko", mfc="none", ms=7)
        est = phone.get("track") or phone.get("batch_estimates")
        ax.plot([e["x"] for e in est], [e["y"] for e in est], ".-", color="tab:orange", ms=2, lw=0.6)
        pdr = phone.get("pdr_only", [])
        ax.plot([e["x"] for e in pdr], [e["y"] for e in pdr], "--", color="tab:green", lw=1)
        mean = np.mean([e["error_m"] for e in est])
        ax.set_title(f"{scenario} / {phone['filter']} (phone {phone.get('phone', 0)}, mean {mean:.2f} m)", fontsize=9)
        ax.grid(alpha=0.2)
    fig.legend(handles=LEGEND, loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(result_files: list[str | Path], out_dir: str | Path) -> dict:
    """Read track results files, write the tables and plots, return the numbers."""
    results = [json.loads(Path(p).read_text()) for p in result_files]
    results = [r for r in results if r.get("kind") == "track"]
    if not results:
        raise ValueError(f"no track results in {', '.join(map(str, result_files))}")
    errs = collect_errors(results)
    table = track_table(results)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "errors.json").write_text(json.dumps({"table": table, "errors": {f"{s}/{f}": e for (s, f), e in errs.items()}}))
    (out / "errors.md").write_text(markdown_table(table))
    plot_cdf(errs, out / "cdf.png")
    plot_trajectories(results, out / "trajectory.png")
    return table


def plot_scenario(world, path: str | Path, seed: int = 0) -> None:
    """Floor plan(s) of a world with transmitters, reference points and one simulated walk."""
    from .phone import simulate_phone

    levels = [f.level for f in world.floors]
    fig, axes = plt.subplots(1, len(levels), figsize=(5 * len(levels), 4.6), squeeze=False, layout="constrained")
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
    handles, _ = axes[0][0].get_legend_handles_labels()
    fig.legend(handles=LEGEND[:3] + handles, loc="outside lower center", ncol=3 * min(len(levels), 2), fontsize=8, frameon=False)
    fig.savefig(path, dpi=110)
    plt.close(fig)
