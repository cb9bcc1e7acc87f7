"""How much of their error a walk's fingerprint fixes share (MSFT site 1 F1): the fix-error
correlation against the distance walked between two fixes.

    python benchmarks/fix_correlation.py [DATA_DIR] [--folds 4] [--algorithm knn]
    python benchmarks/fix_correlation.py --simulator tune [--n 12]     # the simulator's knn fixes
    python benchmarks/fix_correlation.py --by place                     # d between the two places
    python benchmarks/fix_correlation.py --client-sim open_room [--n 6] # client_sim's walks and survey

Per fold (walk i is tested in fold i % 4, as in ``client_sim msft``) a model is trained on the
other walks as the server trains it (``fit_and_validate``: the covariance calibration included),
and every scan of the fold's test walks is located. For each pair of fixes of one walk, d is the
distance walked between them along the waypoint path (``--by place``: the straight distance between
the two true positions, which stays small for a walker who wanders about one spot); printed per band of d: the correlation of
the two fixes' errors (Σ eᵢ·eⱼ / √(Σ|eᵢ|²·Σ|eⱼ|²), raw in metres and whitened by each fix's
calibrated covariance), i.e. the share ρ of a fix's error that a fix d metres on still carries.
``--simulator SPLIT`` measures the same on the knn fixes of ``benchmarks/scenario_family.py``'s
scenarios (its own model per scenario), to compare the simulator's map errors with the real ones;
``--client-sim SCENARIO`` on ``client_sim``'s walks of that world (its survey, one device, fitted as
the server fits it; the first ``--n`` walks as ``benchmarks/tracking_scenarios.py`` walks them).
A tracker that fuses the fixes as independent assumes ρ = 0 at every d (docs/msft-evaluation.md,
"The fixes' shared error as a consider state"). Chooses nothing; a diagnostic for a
training-time estimate of ρ.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.msft_fingerprint import walk_rows  # noqa: E402
from benchmarks.scenario_family import ModelFixes, World, distance_walked, draw, located, walk  # noqa: E402
from benchmarks.shared_data import SHARED_DATA  # noqa: E402
from client_sim.errors import number  # noqa: E402
from client_sim.phone import simulate_phone  # noqa: E402
from client_sim.radio import RadioModel  # noqa: E402
from client_sim.runs import survey_fingerprints  # noqa: E402
from client_sim.world import get_world  # noqa: E402
from server.estimation.fingerprint import FingerprintSet, fit_and_validate, make_model  # noqa: E402
from server.estimation.fingerprint.calibration import whiten  # noqa: E402

#: bands of the distance walked between two fixes (m)
BANDS = [(0.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 1e9)]


def walk_errors(fixes: np.ndarray, covariances: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, ...]:
    """A walk's fix errors (n, 2), the same whitened by the fixes' covariances, and the distance
    walked to each fix (n,); ``truth`` the true positions in walking order."""
    err = fixes - truth
    return err, whiten(err, covariances), distance_walked(truth)


def pair_distances(truth: np.ndarray, walked: np.ndarray, by: str) -> np.ndarray:
    """d of each pair i < j (``np.triu_indices`` order): the distance walked between the two fixes,
    or (``by`` "place") the straight distance between their true positions."""
    i, j = np.triu_indices(len(truth), 1)
    if by == "place":
        return np.hypot(*(truth[j] - truth[i]).T)
    return np.abs(walked[j] - walked[i])


def msft_walks(data_dir: str, folds: int, algorithm: str):
    """Each MSFT test walk's (fixes, calibrated covariances, truth), its fold's model trained on
    the other folds' walks as the server trains it."""
    rows = walk_rows(data_dir, 3.0)[1]
    n = len(rows)
    for k in range(folds):
        fs = FingerprintSet.from_rows([r for j in range(n) if j % folds != k for r in rows[j]])
        model, _ = fit_and_validate(lambda: make_model(algorithm, {}, kinds=["wifi"]), fs, "device")
        for j in range(k, n, folds):
            test = FingerprintSet.from_rows(rows[j]).select_kinds(["wifi"]).drop_empty()
            pred = model.predict(test.aligned_rss(model.tx_ids_), None)
            yield pred.xy, pred.covariance, np.column_stack([test.x, test.y])
        print(f"fold {k}: the map's measured walk share (training, every walk held out once) "
              f"{model.calibration_.walk_share}", flush=True)


def simulator_walks(split: str, n: int):
    """Each simulated scenario's (knn fixes, their covariances, truth), as scenario_family makes them."""
    for i in range(n):
        world = World(draw(split, i))
        w = walk(world)
        pairs = located(w, ModelFixes(world.model("knn")))
        yield (np.array([(f.x, f.y) for f, _ in pairs]), np.array([np.asarray(f.covariance, float) for f, _ in pairs]),
               np.array([p for _, p in pairs]))


def client_sim_walks(scenario: str, n: int, algorithm: str):
    """Each of ``n`` client_sim walks' (fixes, calibrated covariances, truth): the model fitted on the
    world's survey (3 scans per heading, seed 0, as ``tracking_scenarios.py`` surveys it) by
    ``fit_and_validate``, every scan of the walk located."""
    world = get_world(scenario)
    fs = FingerprintSet.from_rows(survey_fingerprints(world, 3, 0))
    model, _ = fit_and_validate(lambda: make_model(algorithm, {}, kinds=None), fs)
    radio = RadioModel(world)
    for w in range(n):
        trace = simulate_phone(world, world.routes[w % len(world.routes)], w, radio=radio)
        scans = [s for s in trace.scans if model.known_transmitters(s["rss"])]
        fixes = model.locate_many([s["rss"] for s in scans], [s.get("heading_deg") for s in scans])
        yield (np.array([(f.x, f.y) for f in fixes]), np.array([np.asarray(f.covariance, float) for f in fixes]),
               np.array([trace.truth_at(s["t"])[:2] for s in scans]))


def band_sums(err: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Per band of the pairs' distances ``d`` (``pair_distances``): [Σ eᵢ·eⱼ, Σ|eᵢ|², Σ|eⱼ|², pairs]
    over the walk's pairs i < j."""
    i, j = np.triu_indices(len(err), 1)
    dot, ni, nj = (err[i] * err[j]).sum(1), (err[i] ** 2).sum(1), (err[j] ** 2).sum(1)
    out = np.zeros((len(BANDS), 4))
    for b, (lo, hi) in enumerate(BANDS):
        m = (d >= lo) & (d < hi)
        out[b] = dot[m].sum(), ni[m].sum(), nj[m].sum(), m.sum()
    return out


def correlation(sums: np.ndarray) -> np.ndarray:
    return sums[:, 0] / np.sqrt(np.maximum(sums[:, 1] * sums[:, 2], 1e-300))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_dir", nargs="?", default=str(SHARED_DATA / "msft_site1_f1"))
    ap.add_argument("--folds", type=number(int, 2), default=4)
    ap.add_argument("--algorithm", default="knn")
    ap.add_argument("--simulator", choices=["tune", "heldout", "stress"], help="the simulator's scenarios instead")
    ap.add_argument("--client-sim", metavar="SCENARIO", help="client_sim's walks of that world instead")
    ap.add_argument("--n", type=number(int, 1), default=12, help="with --simulator: scenarios 0..n-1; with --client-sim: walks")
    ap.add_argument("--by", choices=["walked", "place"], default="walked",
                    help="d: the distance walked between two fixes, or between their true positions")
    a = ap.parse_args()

    if a.simulator:
        walks = simulator_walks(a.simulator, a.n)
        source = f"simulator {a.simulator} 0–{a.n - 1}, knn"
    elif a.client_sim:
        walks = client_sim_walks(a.client_sim, a.n, a.algorithm)
        source = f"client_sim {a.client_sim}, {a.algorithm}"
    else:
        walks = msft_walks(a.data_dir, a.folds, a.algorithm)
        source = f"MSFT, {a.algorithm}, {a.folds} folds"
    raw, white = np.zeros((len(BANDS), 4)), np.zeros((len(BANDS), 4))
    walk_share = []
    for fixes, covariances, truth in walks:
        err, w, walked = walk_errors(fixes, covariances, truth)
        d = pair_distances(truth, walked, a.by)
        raw += band_sums(err, d)
        white += band_sums(w, d)
        walk_share.append(float(np.sum(err.mean(0) ** 2) / np.mean(np.sum(err**2, 1))))
    print(f"{len(walk_share)} walks ({source}); share of a walk's mean squared fix error that is its "
          f"mean error (|ē|² / mean |e|²): median {np.median(walk_share):.2f}, mean {np.mean(walk_share):.2f}")
    what = "distance walked between two fixes" if a.by == "walked" else "distance between two fixes' true positions"
    print(f"| {what} | pairs | error correlation (m) | whitened |")
    print("|---|---|---|---|")
    for b, (lo, hi) in enumerate(BANDS):
        band = f"{lo:g}–{hi:g} m" if hi < 1e8 else f"≥ {lo:g} m"
        print(f"| {band} | {int(raw[b, 3])} | {correlation(raw)[b]:.2f} | {correlation(white)[b]:.2f} |")


if __name__ == "__main__":
    main()
