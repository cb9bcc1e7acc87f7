"""Held-out evaluation of a fingerprint model.

Errors are horizontal Euclidean distances (m) between the estimate and the true
position, whatever the floor (a wrong floor shows up in ``floor_hit_rate``).
``mapping_rate`` is the share of queries whose best reference point is the query's
own reference point (same (building, floor, label) or (building, floor, x, y)).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from .dataset import FingerprintSet, group_split, random_split


@dataclass
class Metrics:
    algorithm: str
    n_train: int
    n_test: int
    mean_error_m: float
    p50_error_m: float
    p90_error_m: float
    mapping_rate: float
    floor_hit_rate: float
    building_hit_rate: float
    fit_time_s: float
    us_per_query: float  # batch prediction, per query
    single_query_us: float  # p50 of one `locate` call (dict in, Fix out)

    def as_api_dict(self) -> dict:
        """The `metrics` object of API.md's Model."""
        return {k: getattr(self, k) for k in
                ("mean_error_m", "p50_error_m", "p90_error_m", "mapping_rate", "floor_hit_rate")}

    def as_dict(self) -> dict:
        return asdict(self)


def evaluate(model, test: FingerprintSet, n_single: int = 200, seed: int = 0) -> Metrics:
    """Metrics of a fitted model on held-out fingerprints ``test`` (NaN figures when no
    test row hears anything, e.g. a split that held out nothing)."""
    test = test.select_kinds(model.kinds).drop_empty() if model.kinds else test.drop_empty()
    n_train = int(getattr(model, "n_fingerprints_", 0))
    fit_time_s = float(getattr(model, "fit_time_s_", float("nan")))
    if not len(test):
        nan = float("nan")
        return Metrics(model.name, n_train, 0, nan, nan, nan, nan, nan, nan, fit_time_s, nan, nan)
    R = test.aligned_rss(model.tx_ids_)
    heading = test.heading_deg if model.use_heading else None
    t0 = time.perf_counter()
    pred = model.predict(R, heading)
    batch_s = time.perf_counter() - t0
    err = np.hypot(pred.x - test.x, pred.y - test.y)
    true_keys = test.rp_keys()
    idx = getattr(model, "rp_key_index_", {})
    true_rp = np.array([idx.get(k, -1) for k in true_keys])
    mapping = float(np.mean(pred.best_rp == true_rp))

    rng = np.random.default_rng(seed)
    pick = rng.choice(len(test), size=min(n_single, len(test)), replace=False)
    scans = test.subset(pick).scans()
    times = []
    for i, s in zip(pick, scans, strict=True):
        if not model.known_transmitters(s):
            continue
        h = None if heading is None or np.isnan(heading[i]) else float(heading[i])
        t1 = time.perf_counter()
        model.locate(s, h)
        times.append(time.perf_counter() - t1)
    return Metrics(
        algorithm=model.name,
        n_train=n_train,
        n_test=len(test),
        mean_error_m=float(np.mean(err)),
        p50_error_m=float(np.percentile(err, 50)),
        p90_error_m=float(np.percentile(err, 90)),
        mapping_rate=mapping,
        floor_hit_rate=float(np.mean(pred.floor == test.floor)),
        building_hit_rate=float(np.mean(pred.building == test.building)),
        fit_time_s=fit_time_s,
        us_per_query=1e6 * batch_s / len(test),
        single_query_us=1e6 * float(np.median(times)) if times else float("nan"),
    )


def holdout_split(fs: FingerprintSet, how: str = "auto", test_fraction: float = 0.2, seed: int = 0):
    """(train, test, description). how: "user", "phone"/"device", "random", a per-row
    group array of ``fs.meta`` (e.g. "power" of the UJI BLE set), or "auto"
    (device groups when there are at least 3 devices, else random)."""
    if how == "auto":
        how = "device" if fs.device is not None and len(set(fs.device.astype(str))) >= 3 else "random"
    if how in ("phone", "device"):
        tr, te, held = group_split(fs, "device", test_fraction, seed)
        return tr, te, f"held-out devices {held}"
    if how == "user":
        tr, te, held = group_split(fs, "user", test_fraction, seed)
        return tr, te, f"held-out users {held}"
    if how == "power" or (how in fs.meta and how != "skipped"):
        tr, te, held = group_split(fs, how, test_fraction, seed)
        return tr, te, f"held-out {how} {held}"
    if how == "random":
        tr, te = random_split(fs, test_fraction, seed)
        return tr, te, f"random {test_fraction:.0%} of rows (seed {seed})"
    raise ValueError(f"unknown split {how!r}")


def fit_and_validate(model_factory, fs: FingerprintSet, how: str = "auto", test_fraction: float = 0.2,
                     seed: int = 0, refit: bool = True):
    """For the server's training job: fit on a held-out split and measure, then (if
    ``refit``) fit a fresh model on all of ``fs``. ``model_factory()`` returns an
    unfitted model. Returns (model, Metrics)."""
    train, test, _ = holdout_split(fs, how, test_fraction, seed)
    m = model_factory().fit(train)
    metrics = evaluate(m, test)
    if refit:
        m = model_factory().fit(fs)
        metrics.fit_time_s = m.fit_time_s_
        metrics.n_train = m.n_fingerprints_
    return m, metrics
