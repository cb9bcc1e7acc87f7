"""Background training of fingerprint models.

A `TrainingWorker` thread claims queued jobs from the database (a compare-and-set, so
several server processes can each run a worker) and runs each in a child process, so
a long fit never holds the request-serving process's interpreter (GIL) or memory. The child loads the
site's fingerprints, measures the model on a bounded held-out sample (and calibrates
its covariance there), refits on everything, measures each floor's grid from the survey
(``building_grid``: the sessions' heading reference where a floor has no plan), and stores the
artifact, its SHA-256 and the metrics in one transaction. Whether the model becomes the site's active one is
decided in that same transaction (`decide_activation`: by default the first ready
model of a site; ``if_better`` also one whose held-out error is no worse).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import signal
import threading
import time
import traceback
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np
from sqlalchemy.exc import IntegrityError

from server.db import Database
from server.domain import Activation, FingerprintRecord, ModelInfo, ModelSpec, Transmitter
from server.estimation.building_grid import survey_grids
from server.estimation.fingerprint import FingerprintSet, checksum, fit_and_validate, make_model, to_bytes
from server.estimation.fingerprint.metrics import PointError, Validation
from server.store import models as store
from server.store import sites as site_store
from server.store import surveys as survey_store

log = logging.getLogger(__name__)

#: Signals that stop a server: blocked while a training child starts, so one sent to the whole
#: process group while it is still importing cannot make it look like a failed job.
_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}

#: How long a worker waits for a stop after its training child died, before calling the job failed.
STOP_GRACE_S = 5.0

#: Below this many fingerprints a held-out split says nothing; the model is fitted without metrics.
MIN_FINGERPRINTS_FOR_VALIDATION = 20


def build_model(algorithm: str, params: dict, use_heading: bool, kinds: list[str] | None, transmitters: list[dict]):
    """An unfitted model; the propagation model also gets the site's positioned transmitters
    (``{id, kind, floor, x, y, tx_power_dbm, path_loss_exponent}`` each)."""
    params = dict(params)
    if algorithm == "propagation":
        params.setdefault("transmitters", transmitters)
    return make_model(algorithm, params, use_heading=use_heading, kinds=kinds or None)


def run_training_job(database_url: str, model_id: int) -> str:
    """Train one claimed model and store the outcome; returns its final status (``gone``: the
    model was deleted meanwhile, or is no longer in training). Runs in a child process.

    Ctrl-C reaches the whole process group: the child ignores SIGINT and leaves stopping to
    its worker, which ends it and hands the job back to the queue."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)  # blocked by the worker until now
    db = Database(database_url)
    try:
        with db.transaction() as s:
            job = store.training_job(s, model_id)
            if job is None:  # the model (or its site) was deleted meanwhile
                return "gone"
            site_id, spec = job.site_id, job.spec
            rows = survey_store.stream_training_rows(s, site_id, spec.include_crowd)
            fs = FingerprintSet.from_rows((_row(r) for r in rows), dtype=_rss_dtype(spec.algorithm))
            transmitters = site_store.positioned_transmitters(s, site_id)
        trained_on = len(fs)
        try:
            model, metrics = _fit(fs if trained_on else None, spec, transmitters)
            # (a crowd fingerprint belongs to no reference point: the store gives it no label)
            model.crowd_share_ = sum(label is None for label in fs.label) / trained_on if trained_on else 0.0
            if metrics is not None:
                metrics["survey_grid"] = _survey_grid(fs, model_id)
                metrics["crowd_share"] = model.crowd_share_
            del fs
            blob = to_bytes(model)
        except Exception as exc:  # any failure of the fit is the job's failure, reported to the admin
            log.warning("training model %s failed:\n%s", model_id, traceback.format_exc())
            with db.transaction() as s:
                store.fail_training(s, model_id, f"{type(exc).__name__}: {exc}")
            return "failed"
        return "ready" if _store(db, site_id, model_id, blob, trained_on, metrics, spec.activate) else "gone"
    finally:
        db.dispose()


def _survey_grid(fs: FingerprintSet, model_id: int) -> list[dict]:
    """The floors' grids from the survey (``building_grid.survey_grids``), as stored in the model's
    metrics. A heading reference for the trackers, not part of the model: should measuring it fail,
    the model is stored without it (as a floor whose survey shows no grid) rather than failing."""
    try:
        return [asdict(g) for g in survey_grids(fs.building, fs.floor, fs.x, fs.y, fs.device, fs.t)]
    except Exception:
        log.warning("model %s: the survey's grid could not be measured; stored without it:\n%s",
                    model_id, traceback.format_exc())
        return []


def _rss_dtype(algorithm: str) -> type:
    """The training matrix's dtype: float16 where exact (whole dBm are; float32 otherwise, see
    ``FingerprintSet.from_rows``) — the models read it through their float32 encoding, so the
    values are those of float32 at half the memory; float32 for the propagation model, whose
    path-loss fit computes on the raw dBm in the matrix's own dtype (float16 would underflow)."""
    return np.float32 if algorithm == "propagation" else np.float16


def _fit(fs: FingerprintSet | None, spec: ModelSpec, transmitters: list[Transmitter]):
    def factory():
        return build_model(spec.algorithm, dict(spec.params), spec.use_heading, list(spec.kinds),
                           [asdict(t) for t in transmitters])

    if fs is None:
        if spec.algorithm != "propagation":
            raise ValueError("the site has no fingerprints to train on")
        return factory().fit(None), None
    if len(fs) < MIN_FINGERPRINTS_FOR_VALIDATION:
        return factory().fit(fs), None
    model, v = fit_and_validate(factory, fs)
    return model, metrics_record(v)


def metrics_record(v: Validation) -> dict[str, Any]:
    """A model's ``metrics`` JSON: the held-out figures, the covariance calibration with the
    held-out NIS before and after it, and each held-out reference point's mean error
    (``points``: [building, floor, x, y, label, n, mean_error_m] rows, bounded by the
    held-out sample). Non-finite figures are null."""
    m = v.metrics
    figures = {**m.as_api_dict(), "fit_time_s": m.fit_time_s, "validated_on": m.n_test,
               "building_hit_rate": m.building_hit_rate, "us_per_query": m.single_query_us,
               "held_out": v.split, "held_out_pooled": v.pooled,
               "calibration": {"scale": v.calibration.scale, "floor_m": v.calibration.floor_m,
                               "walk_share": v.calibration.walk_share},
               "nis_raw": {"mean": v.nis_raw.mean, "median": v.nis_raw.median},
               "nis_calibrated": {"mean": v.nis_calibrated.mean, "median": v.nis_calibrated.median},
               "points": [[p.building, p.floor, round(p.x, 2), round(p.y, 2), p.label, p.n, round(p.mean_error_m, 2)]
                          for p in v.points]}
    return _finite(figures)


def held_out_points(metrics: Mapping[str, Any] | None) -> list[PointError]:
    """The ``points`` of a `metrics_record`, as domain records (none for a model trained on too
    few fingerprints to validate, or before this record existed)."""
    out = []
    for row in (metrics or {}).get("points") or []:
        b, f, x, y, label, n, err = row
        if err is not None:
            out.append(PointError(int(b), int(f), float(x), float(y), str(label), int(n), float(err)))
    return out


def _finite(o: Any) -> Any:
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list):
        return [_finite(v) for v in o]
    return o


def _row(fp: FingerprintRecord) -> dict[str, Any]:
    """A fingerprint as ``FingerprintSet.from_rows`` reads it."""
    return {"x": fp.x, "y": fp.y, "floor": fp.floor, "rss": fp.rss, "heading_deg": fp.heading_deg,
            "device": fp.device, "t": fp.t, "label": fp.label, "building": fp.building}


@dataclass(frozen=True)
class ActivationDecision:
    """Whether a freshly trained model becomes the site's active one, and why (kept in its metrics)."""

    requested: Activation
    activated: bool
    reason: str
    mean_error_m: float | None  # the new model's held-out mean error
    active_model_id: int | None = None  # the model active when it was decided
    active_mean_error_m: float | None = None

    def record(self) -> dict[str, Any]:
        return asdict(self)


def decide_activation(requested: Activation, mean_error_m: float | None, active: ModelInfo | None,
                      pooled: bool = False) -> ActivationDecision:
    """``if_better``: active when no model is, or when its held-out mean error (the same
    figure on both models, each on its own held-out sample) is no worse than the active
    model's; a model without that figure (too few fingerprints to validate) never
    displaces one. ``pooled``: the new figure comes from every device held out once; it is
    not compared with an active model's figure from one split (a model trained before the
    pooled figures: on a site of a few walks one split can be tens of metres off either way),
    and the new model then waits."""
    if active is None:
        return ActivationDecision(requested, requested != "never", "no active model" if requested != "never"
                                  else "activation not requested", mean_error_m)
    theirs = (active.metrics or {}).get("mean_error_m")
    theirs = float(theirs) if isinstance(theirs, (int, float)) else None

    def decided(activated: bool, reason: str) -> ActivationDecision:
        return ActivationDecision(requested, activated, reason, mean_error_m, active.id, theirs)

    if requested == "always":
        return decided(True, "activation requested")
    if requested in ("never", "if_none"):
        return decided(False, f"model {active.id} is active")
    if mean_error_m is None:
        return decided(False, "no held-out error to compare (too few fingerprints to validate)")
    if theirs is None:
        return decided(True, f"the active model {active.id} has no held-out error")
    if pooled != bool((active.metrics or {}).get("held_out_pooled")):
        return decided(False, f"held-out errors not comparable: model {active.id}'s is from "
                              f"{'one split' if pooled else 'every device held out once'}, this model's from "
                              f"{'every device held out once' if pooled else 'one split'}; retrain model "
                              f"{active.id}'s algorithm or activate this one with 'always'")
    if mean_error_m <= theirs:
        return decided(True, f"held-out mean error {mean_error_m:.2f} m ≤ {theirs:.2f} m of model {active.id}")
    return decided(False, f"held-out mean error {mean_error_m:.2f} m > {theirs:.2f} m of model {active.id}")


def _store(db: Database, site_id: int, model_id: int, blob: bytes, trained_on: int, metrics: dict | None,
           requested: Activation) -> bool:
    """Store the outcome if the model is still in training (compare-and-set); False if it was not.
    The activation is decided in the same transaction, against the model active then."""
    error = (metrics or {}).get("mean_error_m")
    for attempt in range(2):
        try:
            with db.transaction() as s:
                decision = decide_activation(requested, error, store.active_model(s, site_id),
                                             bool((metrics or {}).get("held_out_pooled")))
                if attempt:
                    decision = replace(decision, activated=False,
                                       reason="another model of the site became active at the same moment")
                record = {**(metrics or {}), "activation": decision.record()}
                if not store.finish_training(s, model_id, blob, checksum(blob), trained_on, record):
                    return False
                if decision.activated:
                    store.activate_model(s, site_id, model_id)
            return True
        except IntegrityError:
            # Another model of the site became active at the same moment: store this one inactive.
            continue
    return False


class TrainingWorker:
    """Claims queued jobs and trains each in a fresh child process, one at a time.

    A child per job keeps the server's memory flat between jobs, and `stop` can end a
    training in progress (the job goes back to the queue). While a child trains, the worker
    renews the job's claim every ``stale_after_s / 6`` seconds (a heartbeat), so a job is
    claimed again ``stale_after_s`` after its worker died, never while it lives. A child ended
    by SIGTERM or SIGINT (the server is being stopped) hands its job back to the queue.
    """

    def __init__(self, database_url: str, poll_s: float = 2.0, stale_after_s: float = 90.0):
        self.database_url = database_url
        self.poll_s = poll_s
        self.stale_after = timedelta(seconds=stale_after_s)
        self.heartbeat_s = max(min(stale_after_s / 6, 15.0), 0.05)
        self._db = Database(database_url)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self.serve_forever, name="training-worker", daemon=True)
        self._context = multiprocessing.get_context("spawn")

    def start(self) -> TrainingWorker:
        self._thread.start()
        return self

    def wake(self) -> None:
        """Look for jobs now rather than at the next poll."""
        self._wake.set()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30)
        self._db.dispose()

    def run_pending(self) -> int:
        """Train every job that can be claimed now; returns how many ran."""
        done = 0
        while not self._stop.is_set():
            with self._db.transaction() as s:
                model_id = store.claim_next_model(s, datetime.now(UTC) - self.stale_after)
            if model_id is None:
                return done
            self._train(model_id)
            done += 1
        return done

    def _train(self, model_id: int) -> None:
        child = self._context.Process(
            target=run_training_job, args=(self.database_url, model_id), name=f"train-model-{model_id}", daemon=True
        )
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)  # inherited by the child
        try:
            child.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        beat = time.monotonic()
        while child.is_alive() and not self._stop.is_set():
            child.join(timeout=min(0.5, self.heartbeat_s))
            if time.monotonic() - beat >= self.heartbeat_s:
                beat = time.monotonic()
                self._heartbeat(model_id)
        if child.is_alive():  # shutting down: end the fit and hand the job back to the queue
            child.terminate()
            child.join()
        stopped = self._stop.is_set() or child.exitcode in (-signal.SIGTERM, -signal.SIGINT)
        if child.exitcode != 0 and not stopped:
            # A signal to the whole process group may end the child a moment before the server
            # stops this worker: a job is failed only if no stop follows its child's death.
            stopped = self._stop.wait(STOP_GRACE_S)
        if child.exitcode != 0:
            # compare-and-set from "training": a job the child finished keeps its outcome
            with self._db.transaction() as s:
                if stopped:
                    store.requeue_model(s, model_id)
                else:
                    store.fail_training(s, model_id, f"the training process died (exit code {child.exitcode})")

    def _heartbeat(self, model_id: int) -> None:
        try:
            with self._db.transaction() as s:
                store.heartbeat(s, model_id)
        except Exception:  # a database hiccup: the next beat tries again
            log.warning("training worker: heartbeat of model %s failed", model_id, exc_info=True)

    def serve_forever(self) -> None:
        """Poll for jobs until `stop` (runs in the worker thread, or in the foreground for the CLI)."""
        while not self._stop.is_set():
            try:
                self.run_pending()
            except Exception:  # keep the worker alive through a database hiccup; the job stays claimable
                log.exception("training worker")
            self._wake.wait(self.poll_s)
            self._wake.clear()
