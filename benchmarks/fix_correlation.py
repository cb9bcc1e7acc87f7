"""How much of their error a walk's fingerprint fixes share (MSFT site 1 F1): the fix-error
correlation against the distance walked between two fixes.

    python benchmarks/fix_correlation.py [DATA_DIR] [--folds 4] [--algorithm knn]

Per fold (walk i is tested in fold i % 4, as in ``client_sim msft``) a model is trained on the
other walks as the server trains it (``fit_and_validate``: the covariance calibration included),
and every scan of the fold's test walks is located. For each pair of fixes of one walk, d is the
distance walked between them along the waypoint path; printed per band of d: the correlation of
the two fixes' errors (Σ eᵢ·eⱼ / √(Σ|eᵢ|²·Σ|eⱼ|²), raw in metres and whitened by each fix's
calibrated covariance), i.e. the share ρ of a fix's error that a fix d metres on still carries.
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
from benchmarks.shared_data import SHARED_DATA  # noqa: E402
from server.estimation.fingerprint import FingerprintSet, fit_and_validate, make_model  # noqa: E402

#: bands of the distance walked between two fixes (m)
BANDS = [(0.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 1e9)]


def walk_errors(model, rows: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The walk's fix errors (n, 2), the same whitened by their calibrated covariance, and the
    distance walked to each scan (n,), for the scans the model can locate."""
    fs = FingerprintSet.from_rows(rows).select_kinds(["wifi"]).drop_empty()
    pred = model.predict(fs.aligned_rss(model.tx_ids_), None)
    truth = np.column_stack([fs.x, fs.y])
    err = pred.xy - truth
    white = np.stack([np.linalg.solve(np.linalg.cholesky(c), e) for c, e in zip(pred.covariance, err, strict=True)])
    walked = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth, axis=0).T))])
    return err, white, walked


def band_sums(err: np.ndarray, walked: np.ndarray) -> np.ndarray:
    """Per band: [Σ eᵢ·eⱼ, Σ|eᵢ|², Σ|eⱼ|², pairs] over the walk's pairs i < j."""
    i, j = np.triu_indices(len(err), 1)
    d = np.abs(walked[j] - walked[i])
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
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--algorithm", default="knn")
    a = ap.parse_args()

    rows = walk_rows(a.data_dir, 3.0)[1]
    n = len(rows)
    raw, white = np.zeros((len(BANDS), 4)), np.zeros((len(BANDS), 4))
    walk_share = []
    for k in range(a.folds):
        fs = FingerprintSet.from_rows([r for j in range(n) if j % a.folds != k for r in rows[j]])
        model, _ = fit_and_validate(lambda: make_model(a.algorithm, {}, kinds=["wifi"]), fs, "device")
        for j in range(k, n, a.folds):
            err, w, walked = walk_errors(model, rows[j])
            raw += band_sums(err, walked)
            white += band_sums(w, walked)
            walk_share.append(float(np.sum(err.mean(0) ** 2) / np.mean(np.sum(err**2, 1))))
        print(f"fold {k} done", file=sys.stderr, flush=True)
    print(f"{n} walks, {a.algorithm}, {a.folds} folds; share of a walk's mean squared fix error that is its "
          f"mean error (|ē|² / mean |e|²): median {np.median(walk_share):.2f}, mean {np.mean(walk_share):.2f}")
    print("| distance walked between two fixes | pairs | error correlation (m) | whitened |")
    print("|---|---|---|---|")
    for b, (lo, hi) in enumerate(BANDS):
        band = f"{lo:g}–{hi:g} m" if hi < 1e8 else f"≥ {lo:g} m"
        print(f"| {band} | {int(raw[b, 3])} | {correlation(raw)[b]:.2f} | {correlation(white)[b]:.2f} |")


if __name__ == "__main__":
    main()
