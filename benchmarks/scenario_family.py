"""A family of simulated walks for tuning and for held-out evaluation of the trackers.

    python benchmarks/scenario_family.py --split heldout --n 12 [--fixes knn|gaussian|both|shared]
    python benchmarks/scenario_family.py --split tune --n 12 --filters ekf,ekf-xy

Written apart from ``client_sim`` (its own world, radio and PDR error model) and run
offline through ``SessionEstimator.apply_batch`` in 2 s batches, with the session going
through JSON between batches as the server stores it. Each scenario is a rectangular
corridor loop with WiFi APs and iBeacons placed at random around it, a log-distance
radio with a fixed spatial shadowing field per transmitter, body shadowing (a
transmitter behind the walker is weaker) and per-scan noise; a fingerprint model
(``--algorithm``) fitted as the server's training job fits it (held-out validation and a
calibrated covariance) on a survey every 2 m of the loop (3 scans per point, averaged), whose
positions also give the floor its grid direction as the server's training measures it
(``building_grid.survey_grids``: the sessions' heading reference on a floor without a plan); a walker whose PDR has a
heading bias that drifts linearly, a step-length bias and white noise, and who sends
steps **without** std fields (the server's defaults apply).

Parameters are drawn per scenario from ranges; the ``tune`` and ``heldout`` ranges do
not overlap on any parameter (drift rate, initial bias, length bias, heading noise, radio
noise and shadowing, transmitter count, loop size, laps), and seeds differ. Tracker
defaults are chosen on ``tune`` only; ``heldout`` reports. ``stress`` is harsher than
``heldout`` on every PDR and radio parameter (larger loops, one lap; its own seeds): where
remedies for failures the tune ranges never show (a PF cloud collapsing at walls) are
chosen, apart from ``heldout``.

With ``--fixes gaussian`` the fixes are unbiased: the truth plus N(0, σ²I) with the
honest covariance σ²I (the fix quality drawn from the split's range); that is where
the share of refused fixes must stay below 5 %. With ``--fixes shared`` (not in ``both``) the
fixes' error is shared along the walk as on the real MSFT walks (``fix_correlation.py``: the
knn fixes here share ≈ 0.02 of their error over a walk, MSFT's ≈ 0.47): the truth plus a
walk-constant offset (variance ``SHARED_WALK``·σ²), a part that decays over
``SHARED_LENGTH_M`` walked (``SHARED_DECAYING``·σ²) and white noise (the rest), declared with
the same honest marginal covariance σ²I.

Figures per method: mean / p90 error (m) over every estimate of every scenario; the
position NEES (2-D; mean and median over step estimates, 2 is consistent, the share above
50: a PF cloud collapsed onto a few points, and the smoothed track's mean); the NIS of the fixes
(mean over fixes, 2 is consistent; before any inflation); the share of fixes refused by
the innovation gate; and the mean error of the track after the RTS smoother
(``server/estimation/tracking/smoother.py``, run on the stored track as a replay would; for a
PF also, under the table, its particle smoother as ``smoother=particles`` serves it, the walk
replayed from its recorded batches: ``server/estimation/replay.py``);
and the mean size of the session's stored state (JSON, kB) per batch.

With ``--plan`` the floor has the loop's plan: a corridor ``--corridor-m`` wide around the
centre-line (its walls, and its walkable area as the server holds an imported plan), so the
PF's walls and the session's walkable estimates work as on a site with a floor plan; the
scenarios' draws are the same with or without it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from client_sim.errors import number  # noqa: E402
from server.estimation.building_grid import survey_grids  # noqa: E402
from server.estimation.fingerprint import FingerprintSet, make_model  # noqa: E402
from server.estimation.fingerprint.metrics import fit_and_validate  # noqa: E402
from server.estimation.floorplan import Walkable  # noqa: E402
from server.estimation.replay import RecordingFixes, replays, smoothed_by_replay  # noqa: E402
from server.estimation.session import SessionEstimator  # noqa: E402
from server.estimation.tracking.landmarks import LandmarkCorrector  # noqa: E402
from server.estimation.tracking.particle_smoother import DEFAULT_LAG  # noqa: E402
from server.estimation.tracking.smoother import smooth_track  # noqa: E402
from server.estimation.types import Area, Beacon, Estimate, Fix, InitialHeading, NoFix, Scan, SiteMap, Step, step_displacement  # noqa: E402

FILTERS = ("ekf", "ukf", "pf", "skpf", "ekf-xy", "ukf-xy", "pf-xy", "skpf-xy", "kf", "fkf")

#: (low, high) per parameter; a "±" parameter gets a random sign
RANGES = {
    "tune": {
        "drift_deg_per_step": (0.0, 0.08), "bias0_deg": (0.0, 3.0), "length_bias": (0.0, 0.03),
        "heading_white_deg": (2.0, 4.0), "scan_noise_db": (2.0, 3.0), "shadow_db": (2.0, 3.0),
        "n_tx": (9, 12), "width_m": (30.0, 40.0), "height_m": (14.0, 20.0), "laps": (1, 1),
        "gauss_fix_std_m": (1.0, 2.0),
    },
    "heldout": {
        "drift_deg_per_step": (0.1, 0.25), "bias0_deg": (4.0, 10.0), "length_bias": (0.04, 0.10),
        "heading_white_deg": (4.5, 7.0), "scan_noise_db": (3.5, 5.0), "shadow_db": (3.5, 5.0),
        "n_tx": (5, 8), "width_m": (42.0, 60.0), "height_m": (21.0, 30.0), "laps": (2, 3),
        "gauss_fix_std_m": (2.2, 3.5),
    },
    # harsher than heldout (larger loops, one lap): for choosing what the tune ranges never need
    "stress": {
        "drift_deg_per_step": (0.28, 0.4), "bias0_deg": (11.0, 16.0), "length_bias": (0.11, 0.15),
        "heading_white_deg": (7.5, 9.0), "scan_noise_db": (5.5, 6.5), "shadow_db": (5.5, 6.5),
        "n_tx": (4, 4), "width_m": (61.0, 72.0), "height_m": (31.0, 36.0), "laps": (1, 1),
        "gauss_fix_std_m": (3.7, 4.5),
    },
}
SIGNED = ("drift_deg_per_step", "bias0_deg", "length_bias")
SEED_BASE = {"tune": 10_000, "heldout": 20_000, "stress": 30_000}


@dataclass(frozen=True)
class Scenario:
    split: str
    index: int
    seed: int
    drift_deg_per_step: float
    bias0_deg: float
    length_bias: float
    heading_white_deg: float
    scan_noise_db: float
    shadow_db: float
    n_tx: int
    width_m: float
    height_m: float
    laps: int
    gauss_fix_std_m: float


def draw(split: str, index: int) -> Scenario:
    seed = SEED_BASE[split] + index
    rng = np.random.default_rng(seed)
    vals: dict = {}
    for k, (lo, hi) in RANGES[split].items():
        if isinstance(lo, int):
            vals[k] = int(rng.integers(lo, int(hi) + 1))
        else:
            v = float(rng.uniform(lo, hi))
            vals[k] = v * (1 if k not in SIGNED or rng.random() < 0.5 else -1)
    return Scenario(split, index, seed, **vals)


# --------------------------------------------------------------------------- world
class World:
    """The loop's corridor centre-line is the rectangle [0, W] × [0, H]."""

    def __init__(self, sc: Scenario):
        rng = np.random.default_rng(sc.seed + 1)
        self.sc = sc
        W, H = sc.width_m, sc.height_m
        n = sc.n_tx
        # transmitters at random around the loop, up to 6 m off the corridor; 1 in 3 an iBeacon
        t = rng.uniform(0, 2 * (W + H), n)
        self.tx_xy = np.array([self.loop_point(u) for u in t]) + rng.uniform(-6, 6, (n, 2))
        self.tx_ids = [f"ble:b{i}" if i % 3 == 0 else f"wifi:ap{i}" for i in range(n)]
        self.r0 = rng.uniform(-45.0, -35.0, n)
        self.gamma = rng.uniform(2.0, 3.0, n)
        # fixed spatial shadowing: per transmitter a sum of 8 random plane waves (4-15 m)
        k = 8
        lam = rng.uniform(4.0, 15.0, (n, k))
        ang = rng.uniform(0, 2 * math.pi, (n, k))
        self.kx, self.ky = 2 * math.pi / lam * np.cos(ang), 2 * math.pi / lam * np.sin(ang)
        self.phase = rng.uniform(0, 2 * math.pi, (n, k))
        self.shadow_amp = sc.shadow_db * math.sqrt(2.0 / k)

    def loop_point(self, u: float) -> np.ndarray:
        W, H = self.sc.width_m, self.sc.height_m
        u = u % (2 * (W + H))
        if u < W:
            return np.array([u, 0.0])
        if u < W + H:
            return np.array([W, u - W])
        if u < 2 * W + H:
            return np.array([W - (u - W - H), H])
        return np.array([0.0, H - (u - 2 * W - H)])

    def rss(self, xy, heading_deg: float | None, rng: np.random.Generator | None) -> dict[str, float]:
        d = np.maximum(np.hypot(*(self.tx_xy - xy).T), 1.0)
        shadow = self.shadow_amp * np.cos(self.kx * xy[0] + self.ky * xy[1] + self.phase).sum(axis=1)
        v = self.r0 - 10 * self.gamma * np.log10(d) + shadow
        if heading_deg is not None:  # body shadowing: up to 5 dB for a transmitter behind
            h = math.radians(heading_deg)
            to_tx = (self.tx_xy - xy) / d[:, None]
            v -= 5.0 * 0.5 * (1 - (to_tx[:, 0] * math.sin(h) + to_tx[:, 1] * math.cos(h)))
        if rng is not None:
            v = v + rng.normal(0.0, self.sc.scan_noise_db, v.size)
        return {k: float(x) for k, x, dd in zip(self.tx_ids, v, d, strict=True) if x > -95.0 and dd < 60}

    def site(self) -> SiteMap:
        return SiteMap(beacons={k: Beacon(k, float(x), float(y), 0, float(r0), float(g))
                                for k, (x, y), r0, g in zip(self.tx_ids, self.tx_xy, self.r0, self.gamma, strict=True)
                                if k.startswith("ble:")})

    def plan(self, corridor_m: float) -> tuple[list, Walkable]:
        """The loop's walls (the outer and inner rectangles) and its walkable area (four
        overlapping strips: the stored form of an area is hole-free polygons), ``corridor_m`` wide."""
        W, H, c = self.sc.width_m, self.sc.height_m, corridor_m / 2
        outer = [(-c, -c), (W + c, -c), (W + c, H + c), (-c, H + c)]
        inner = [(c, c), (W - c, c), (W - c, H - c), (c, H - c)]
        walls = [[*r[i], *r[(i + 1) % 4]] for r in (outer, inner) for i in range(4)]
        strips = [(-c, -c, W + c, c), (-c, H - c, W + c, H + c), (-c, -c, c, H + c), (W - c, -c, W + c, H + c)]
        return walls, Walkable([[[x0, y0], [x1, y0], [x1, y1], [x0, y1]] for x0, y0, x1, y1 in strips])

    def survey_points(self) -> np.ndarray:
        """Where the survey stands: every 2 m along the loop."""
        return np.array([self.loop_point(float(u)) for u in np.arange(0.0, 2 * (self.sc.width_m + self.sc.height_m), 2.0)])

    def grids(self) -> dict[tuple[int, int], float]:
        """The floor's grid as the server's training measures it from this survey (``building_grid``)."""
        xy = self.survey_points()
        return {(g.building, g.floor): g.deg for g in survey_grids(np.zeros(len(xy)), np.zeros(len(xy)), xy[:, 0], xy[:, 1])}

    def model(self, algorithm: str = "knn"):
        rng = np.random.default_rng(self.sc.seed + 2)
        rows = []
        for p in self.survey_points():
            scans = [self.rss(p, None, rng) for _ in range(3)]
            if SURVEY_ROWS[0] == "scans":  # each scan its own fingerprint, as a survey tool uploads them
                rows += [{"x": float(p[0]), "y": float(p[1]), "floor": 0, "rss": dict(s)} for s in scans if s]
                continue
            keys = set().union(*scans)
            rows.append({"x": float(p[0]), "y": float(p[1]), "floor": 0,
                         "rss": {k: float(np.mean([s.get(k, -100.0) for s in scans])) for k in keys}})
        # as the server's training job fits it: held-out validation, calibrated covariance
        model, _ = fit_and_validate(lambda: make_model(algorithm, dict(MODEL_PARAMS), use_heading=False, kinds=None),
                                    FingerprintSet.from_rows(rows))
        return model


@dataclass
class Walk:
    truth: np.ndarray  # (n + 1, 2)
    steps: list[Step]
    scans: list[Scan]
    scan_truth: np.ndarray


def walk(world: World) -> Walk:
    sc = world.sc
    rng = np.random.default_rng(sc.seed + 3)
    per = 2 * (sc.width_m + sc.height_m)
    true_len = rng.uniform(0.62, 0.78)
    u, t, k = 0.0, 0.0, 0
    truth = [world.loop_point(0.0)]
    steps, scans, scan_truth = [], [], []
    while u + true_len <= sc.laps * per:
        u += true_len * (1 + 0.05 * rng.standard_normal())
        a, b = truth[-1], world.loop_point(u)
        t += 0.55
        k += 1
        true_h = math.degrees(math.atan2(b[0] - a[0], b[1] - a[1]))
        truth.append(b)
        err_h = sc.bias0_deg + sc.drift_deg_per_step * k + sc.heading_white_deg * rng.standard_normal()
        length = float(np.hypot(*(b - a))) * (1 + sc.length_bias) + 0.05 * rng.standard_normal()
        steps.append(Step(t, max(length, 0.05), (true_h + err_h) % 360.0))  # no std fields: defaults
        if k % 2 == 0:
            scans.append(Scan(t + 0.1, world.rss(b, true_h, rng)))
            scan_truth.append(b)
    return Walk(np.array(truth), steps, scans, np.array(scan_truth))


def distance_walked(points: np.ndarray) -> np.ndarray:
    """Metres walked from the first of ``points`` (n, 2) to each, along them."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])


def has_snap(sc: Scenario) -> bool:
    """Whether the scenario's walk triggers a landmark snap (an iBeacon's filtered RSS entering its
    strong zone): what ``--with-snap`` keeps, chosen on the inputs, before any tracker runs."""
    world = World(sc)
    corrector = LandmarkCorrector({k: (b.x, b.y) for k, b in world.site().beacons.items()})
    return any(corrector.observe(s.rss) for s in walk(world).scans)


class ModelFixes:
    def __init__(self, model, cov_scale: float = 1.0):
        self.model, self.cov_scale = model, cov_scale

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        if not scan.rss:
            raise NoFix("the scan heard nothing")
        f = self.model.locate(scan.rss, near=None if near is None else (near.x, near.y),
                              radius_m=None if near is None else near.radius_m)
        return replace(f, covariance=np.asarray(f.covariance) * self.cov_scale)  # (as the server serves it)


class GaussianFixes:
    """Unbiased fixes with their honest covariance."""

    #: the share of a fix's variance that the walk's fixes have in common (``Fix.shared_share``)
    share: float | None = None

    def __init__(self, w: Walk, std_m: float, seed: int):
        rng = np.random.default_rng(seed)
        self.by_t = {s.t: p + std_m * rng.standard_normal(2) for s, p in zip(w.scans, w.scan_truth, strict=True)}
        self.cov = np.eye(2) * std_m**2

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        z = self.by_t[scan.t]
        return Fix(float(z[0]), float(z[1]), 0, self.cov, shared_share=self.share)


#: shares of a ``SharedFixes`` fix's variance: constant over the walk, decaying over SHARED_LENGTH_M
#: (from MSFT site 1's knn fixes, benchmarks/fix_correlation.py: whitened correlation ≈ 0.45 beyond
#: 10 m walked, ≈ 0.8 within 2 m)
SHARED_WALK, SHARED_DECAYING, SHARED_LENGTH_M = 0.45, 0.35, 8.0


class SharedFixes(GaussianFixes):
    """Fixes whose error a walk shares (see the module's ``--fixes shared``), declared with
    their honest marginal covariance σ²I and the walk-constant share (as a map whose training
    measured it declares its ``walk_share``)."""

    share = SHARED_WALK

    def __init__(self, w: Walk, std_m: float, seed: int):
        rng = np.random.default_rng(seed)
        offset = math.sqrt(SHARED_WALK) * std_m * rng.standard_normal(2)
        walked = distance_walked(w.scan_truth)
        slow, errors = rng.standard_normal(2), []
        for k in range(len(walked)):
            if k:
                phi = math.exp(-(walked[k] - walked[k - 1]) / SHARED_LENGTH_M)
                slow = phi * slow + math.sqrt(1 - phi * phi) * rng.standard_normal(2)
            white = math.sqrt(1 - SHARED_WALK - SHARED_DECAYING) * rng.standard_normal(2)
            errors.append(offset + std_m * (math.sqrt(SHARED_DECAYING) * slow + white))
        self.by_t = {s.t: p + e for s, p, e in zip(w.scans, w.scan_truth, errors, strict=True)}
        self.cov = np.eye(2) * std_m**2


def located(w: Walk, fixes: GaussianFixes | ModelFixes) -> list[tuple[Fix, np.ndarray]]:
    """Each scan's fix (no search area) with the true position, for the scans that give one."""
    out = []
    for s, p in zip(w.scans, w.scan_truth, strict=True):
        try:
            out.append((fixes.fix(s, None), p))
        except Exception:  # noqa: BLE001 - nothing known heard
            continue
    return out


# --------------------------------------------------------------------------- running
#: the fingerprint model of the ``knn`` fixes (``--algorithm``)
ALGORITHM = ["knn"]
#: the survey's fingerprints: "mean" (each point's 3 scans averaged, the family's definition) or "scans"
#: (each scan its own row; ``--survey-rows``, a diagnostic of how the calibration transfers)
SURVEY_ROWS = ["mean"]
MODEL_PARAMS: dict = {}  # the fingerprint model's params (--model-params)
#: tracker keyword arguments per filter name (``--set``)
PARAMS: dict[str, dict] = {}
#: the corridor's width when the floor has the loop's plan (``--plan``; None: no plan)
CORRIDOR_M: list[float | None] = [None]
#: the PF's particle smoother's lag (``--lag``)
LAG = [DEFAULT_LAG]
#: sessions open without an initial position (``--cold``): the first scan's fix starts them
COLD = [False]
#: σ (degrees) with which sessions are told the walker's true direction at the start
#: (``--initial-heading-std``; None: not told)
INITIAL_HEADING_STD: list[float | None] = [None]


@dataclass
class Replay:
    """A walk replayed as the server runs a session: its track, the trackers' whole states as the
    server stores them with it, the gate's innovations and the stored session size per batch."""

    estimator: SessionEstimator
    #: the state right after the start, and each batch as recorded (``server.estimation.replay``)
    opening: dict = field(default_factory=dict)
    batches: list = field(default_factory=list)
    track: list = field(default_factory=list)
    states: list = field(default_factory=list)
    innovations: list = field(default_factory=list)
    state_bytes: list = field(default_factory=list)


def replay(name: str, w: Walk, fixes, site: SiteMap, batch_s: float = 2.0) -> Replay:
    """A batch every ``batch_s`` s, the session stored and loaded between batches (as the server does)."""
    est = SessionEstimator(name, seed=7, tracker_params=PARAMS.get(name))
    if not COLD[0]:
        std = INITIAL_HEADING_STD[0]
        est.start(w.truth[0], None, 0, [], None, "init",
                  heading=None if std is None else InitialHeading(initial_direction_deg(w), std))
    out = Replay(est, opening=json.loads(json.dumps(est.to_dict())))
    steps, scans = list(w.steps), list(w.scans)
    t_end = batch_s
    while steps or scans:
        bs = [s for s in steps if s.t < t_end]
        bc = [s for s in scans if s.t < t_end]
        steps, scans = steps[len(bs):], scans[len(bc):]
        stored = json.dumps(est.to_dict())
        out.state_bytes.append(len(stored))
        est = out.estimator = SessionEstimator.from_dict(json.loads(stored))
        est.innovations = []
        recording = RecordingFixes(fixes)
        batch = est.apply_batch(bs, bc, recording, site)
        out.batches.append(recording.batch(bs, bc))
        out.innovations += est.innovations
        out.track += batch.estimates
        out.states += batch.states
        t_end += batch_s
    return out


def errors_and_nees(track, truth_by_t: dict) -> tuple[list[float], list[float]]:
    """Every estimate's error (m) and every step estimate's position NEES, against the truth at its time."""
    errors, nees = [], []
    for e in track:
        d = np.array([e.x, e.y]) - truth_by_t[e.t]
        errors.append(float(np.hypot(*d)))
        if e.source == "step":
            nees.append(float(d @ np.linalg.solve(np.array(e.covariance), d)))
    return errors, nees


def run_filter(name: str, w: Walk, fixes, site: SiteMap, batch_s: float = 2.0) -> dict:
    r = replay(name, w, fixes, site, batch_s)
    truth_by_t = {s.t: p for s, p in zip(w.steps, w.truth[1:], strict=True)}
    truth_by_t.update({s.t: p for s, p in zip(w.scans, w.scan_truth, strict=True)})
    errors, nees = errors_and_nees(r.track, truth_by_t)
    nis = [d2 for d2, _ in r.innovations]
    smoothed, smoothed_nees = errors_and_nees(smooth_track(r.track, site.walkable, r.states), truth_by_t)
    particles: dict = {}
    if replays(name):  # the PF's particle smoother as the server serves it (``smoother=particles``), by replay
        start = [] if r.opening["estimate"] is None else [Estimate.from_dict(r.opening["estimate"])]
        by_replay = smoothed_by_replay(r.opening, r.batches, site, [*start, *r.track], LAG[0])
        if by_replay is None:
            raise RuntimeError(f"{name}: the replay did not reproduce the track")
        particles = dict(zip(("particles", "particles_nees"), errors_and_nees(by_replay[len(start):], truth_by_t),
                             strict=True))
    return {"errors": errors, "smoothed": smoothed, "smoothed_nees": smoothed_nees, "nees": nees, "nis": nis,
            **particles,
            "refused": sum(not ok for _, ok in r.innovations), "fixes": len(r.innovations),
            "state_bytes": r.state_bytes, "bias_deg": getattr(r.estimator.tracker, "heading_bias_deg", None)}


def pdr_errors(w: Walk, turn_deg: float = 0.0) -> list[float]:
    """PDR alone from the true start; ``turn_deg``: every step's heading turned by it."""
    pos = np.cumsum([w.truth[0]] + [step_displacement(s.length_m, s.heading_deg + turn_deg) for s in w.steps], axis=0)
    return np.hypot(*(pos[1:] - w.truth[1:]).T).tolist()


def initial_direction_deg(w: Walk) -> float:
    """The walker's true direction over the first step (degrees clockwise from +y)."""
    dx, dy = np.asarray(w.truth[1], float) - np.asarray(w.truth[0], float)
    return math.degrees(math.atan2(dx, dy))


def baselines() -> list[str]:
    """PDR alone, with ``pdr-aligned`` (the phone's PDR turned by the start's true direction against
    its first step) when sessions are told it, and fingerprinting alone."""
    return ["pdr-only", *(["pdr-aligned"] if INITIAL_HEADING_STD[0] is not None else []), "fingerprint-only"]


def run_scenario(sc: Scenario, filters, fix_kind: str, cov_scale: float) -> dict:
    world = World(sc)
    w = walk(world)
    fixes: GaussianFixes | ModelFixes
    if fix_kind in ("gaussian", "shared"):
        fixes = (GaussianFixes if fix_kind == "gaussian" else SharedFixes)(w, sc.gauss_fix_std_m, sc.seed + 4)
        site = SiteMap()
    else:
        fixes = ModelFixes(world.model(ALGORITHM[0]), cov_scale)
        site = world.site()
    fp = [float(np.hypot(f.x - p[0], f.y - p[1])) for f, p in located(w, fixes)]
    site = replace(site, grids=world.grids())
    if CORRIDOR_M[0] is not None:
        walls, walkable = world.plan(CORRIDOR_M[0])
        site = replace(site, walls={(0, 0): walls}, walkable={(0, 0): walkable})
    out = {"pdr-only": {"errors": pdr_errors(w)}, "fingerprint-only": {"errors": fp}}
    if INITIAL_HEADING_STD[0] is not None:
        out["pdr-aligned"] = {"errors": pdr_errors(w, initial_direction_deg(w) - w.steps[0].heading_deg)}
    for name in filters:
        out[name] = run_filter(name, w, fixes, site)
    return out


def table(results: list[dict], methods) -> list[dict]:
    rows = []
    for m in methods:
        errs = np.concatenate([r[m]["errors"] for r in results if m in r])
        row = {"method": m, "mean": float(errs.mean()), "p90": float(np.percentile(errs, 90))}
        if "nees" in results[0].get(m, {}):
            row["smoothed"] = float(np.mean(np.concatenate([r[m]["smoothed"] for r in results])))
            if "particles" in results[0][m]:
                row["particles"] = float(np.mean(np.concatenate([r[m]["particles"] for r in results])))
                row["particles_nees"] = float(np.mean(np.concatenate([r[m]["particles_nees"] for r in results])))
            smoothed_nees = np.concatenate([r[m]["smoothed_nees"] for r in results])
            row["smoothed_nees"] = float(np.mean(smoothed_nees))
            row["smoothed_nees_p50"] = float(np.median(smoothed_nees))
            nees = np.concatenate([r[m]["nees"] for r in results])
            row["nees"] = float(np.mean(nees))
            row["nees_p50"] = float(np.median(nees))
            row["nees_over_50_pct"] = 100.0 * float(np.mean(nees > 50))
            row["nees_over_1000"] = int(np.sum(nees > 1000))  # (a collapsed cloud; in --out only)
            nis = np.concatenate([r[m]["nis"] for r in results])
            row["nis"] = float(nis.mean()) if nis.size else float("nan")
            fx = sum(r[m]["fixes"] for r in results)
            row["refused_pct"] = 100.0 * sum(r[m]["refused"] for r in results) / max(fx, 1)
            row["state_kb"] = float(np.mean(np.concatenate([r[m]["state_bytes"] for r in results]))) / 1000
        rows.append(row)
    return rows


def markdown(rows: list[dict], title: str) -> str:
    pdr = next(r["mean"] for r in rows if r["method"] == "pdr-only")
    fp = next(r["mean"] for r in rows if r["method"] == "fingerprint-only")
    lines = [f"{title}", "", "| method | mean m | p90 m | vs PDR | vs fingerprint | smoothed m | NEES mean | NEES p50 "
             "| NEES > 50 | smoothed NEES | NIS mean | refused | state kB |", "|---" * 13 + "|"]
    for r in rows:
        if "nees" in r:
            extra = (f"{100 * (r['mean'] / pdr - 1):+.0f} % | {100 * (r['mean'] / fp - 1):+.0f} % | {r['smoothed']:.2f} | "
                     f"{r['nees']:.2f} | {r['nees_p50']:.2f} | {r['nees_over_50_pct']:.1f} % | {r['smoothed_nees']:.2f} | "
                     f"{r['nis']:.2f} | {r['refused_pct']:.1f} % | {r['state_kb']:.1f} |")
        else:
            extra = "— | — | — | — | — | — | — | — | — | — |"
        lines.append(f"| {r['method']} | {r['mean']:.2f} | {r['p90']:.2f} | {extra}")
    lines += [f"\n{r['method']} smoothed by its particles (smoother=particles, lag {LAG[0]}): {r['particles']:.2f} m, "
              f"NEES {r['particles_nees']:.2f}" for r in rows if "particles" in r]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=sorted(RANGES), default="heldout")
    ap.add_argument("--n", type=number(int, 1), default=12, help="scenarios")
    ap.add_argument("--first", type=number(int, 0), default=0, help="index of the first scenario")
    ap.add_argument("--filters", default=",".join(FILTERS))
    ap.add_argument("--fixes", choices=("knn", "gaussian", "both", "shared"), default="both",
                    help="knn: the fixes of a fingerprint model (--algorithm), gaussian: truth plus Gaussian noise, "
                         "both: those two, shared: truth plus an error shared along the walk as on real walks")
    ap.add_argument("--cov-scale", type=number(float, 0, above=True), default=1.0,
                    help="multiply the model's (already calibrated) fix covariance by this (default 1: as served)")
    ap.add_argument("--algorithm", default="knn", help="fingerprint model for the model fixes (knn, wknn, ...)")
    ap.add_argument("--model-params", type=json.loads, default={},
                    help='the fingerprint model\'s params as JSON, e.g. \'{"offset_estimate": false}\'')
    ap.add_argument("--set", action="append", default=[], metavar="FILTER.PARAM=VALUE",
                    help="a tracker parameter, e.g. ekf.bias_walk_deg=0.5 (repeatable)")
    ap.add_argument("--survey-rows", choices=("mean", "scans"), default="mean",
                    help="the survey's 3 scans per point averaged into one fingerprint (the family's definition) "
                         "or uploaded as 3 fingerprints (a diagnostic)")
    ap.add_argument("--plan", action="store_true", help="the floor has the loop's plan (walls and walkable area)")
    ap.add_argument("--corridor-m", type=number(float, 0, above=True), default=3.0, help="the corridor's width with --plan (m)")
    ap.add_argument("--compass-off", type=float, default=None, metavar="DEG",
                    help="every scenario's PDR starts DEG off (the sign of its drawn initial bias): a compass far "
                         "off at the start, as on 2 of the 43 MSFT walks (≈ 45°); the other draws are unchanged")
    ap.add_argument("--with-snap", action="store_true",
                    help="only the scenarios among --first/--n whose walk triggers a landmark snap")
    ap.add_argument("--lag", type=number(int, 0), default=DEFAULT_LAG,
                    help="the PF's particle smoother's lag (estimates; the server's default)")
    ap.add_argument("--cold", action="store_true",
                    help="sessions open without an initial position: the first scan's fix starts them (cold start; "
                         "PDR alone still starts at the truth)")
    ap.add_argument("--initial-heading-std", type=number(float, 0, above=True), default=None, metavar="DEG",
                    help="sessions are told the walker's true direction at the start with this σ (initial.heading_std_deg); "
                         "adds pdr-aligned, the PDR turned by the same knowledge")
    ap.add_argument("--out", type=Path, default=None, help="JSON with every scenario's parameters and figures")
    a = ap.parse_args()
    LAG[0] = a.lag
    COLD[0] = a.cold
    INITIAL_HEADING_STD[0] = a.initial_heading_std
    filters = [f for f in a.filters.split(",") if f]
    ALGORITHM[0] = a.algorithm
    SURVEY_ROWS[0] = a.survey_rows
    MODEL_PARAMS.update(a.model_params)
    CORRIDOR_M[0] = a.corridor_m if a.plan else None
    for item in a.set:
        key, value = item.split("=", 1)
        flt, param = key.split(".", 1)
        PARAMS.setdefault(flt, {})[param] = float(value)
    scenarios = [draw(a.split, i) for i in range(a.first, a.first + a.n)]
    if a.compass_off is not None:
        scenarios = [replace(s, bias0_deg=math.copysign(a.compass_off, s.bias0_deg)) for s in scenarios]
    if a.with_snap:
        scenarios = [s for s in scenarios if has_snap(s)]
    cov_scale = a.cov_scale
    report = {"split": a.split, "scenarios": [asdict(s) for s in scenarios], "cov_scale": cov_scale}
    kinds = ("knn", "gaussian") if a.fixes == "both" else (a.fixes,)
    for kind in kinds:
        t0 = time.perf_counter()
        results = [run_scenario(s, filters, kind, cov_scale) for s in scenarios]
        rows = table(results, [*baselines(), *filters])
        what = f"{a.algorithm} model" if kind == "knn" else kind  # ("knn": the model's fixes, of --algorithm)
        title = (f"{a.split} scenarios {a.first}-{a.first + a.n - 1}"
                 f"{f' ({len(scenarios)} with a landmark snap)' if a.with_snap else ''}, {what} fixes"
                 f"{f', the compass {a.compass_off:g}° off at the start' if a.compass_off is not None else ''}"
                 f"{f', plan (corridor {a.corridor_m:g} m)' if a.plan else ''}"
                 f"{', survey scans as rows' if a.survey_rows == 'scans' else ''}"
                 f"{', cold start' if a.cold else ''}"
                 f"{f', initial heading told (σ {a.initial_heading_std:g}°)' if a.initial_heading_std else ''} "
                 f"({time.perf_counter() - t0:.0f} s)")
        print(markdown(rows, title))
        print()
        report[kind] = rows
        report[f"{kind}_per_scenario_mean"] = {m: [float(np.mean(r[m]["errors"])) if len(r[m]["errors"]) else None
                                                   for r in results]
                                               for m in [*baselines(), *filters]}
        biases = {f: [round(r[f]["bias_deg"], 1) for r in results if r[f].get("bias_deg") is not None]
                  for f in filters}
        report[f"{kind}_final_bias_deg"] = {f: b for f, b in biases.items() if b}
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
