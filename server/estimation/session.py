"""One walking session's tracking, batch by batch: the whole algorithm, free of web and database.

``SessionEstimator.apply_batch`` takes a batch's steps and scans, a ``FixSource`` (what
turns a scan into a fingerprint fix: the server's positioning service, or anything a test
or an offline evaluation supplies) and the site's map, and returns a ``BatchOutcome``. It
orders the inputs by time, refuses inputs older than the last applied one, starts a
session without a given position on its first fix (the cold-start fusion of DESIGN.md),
predicts with steps, updates with fixes through an innovation gate, follows floors with
hysteresis, ranges to beacons, snaps to landmarks and proposes crowd fingerprints.

A floor is a (building, level) pair: the floor hysteresis follows the pair, so a fix in
another building is a floor change like any other, and every estimate's level belongs to
its building.

The state is plain data (``to_dict``/``from_dict``), so the server stores it after every
batch and any process resumes it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from server.estimation.fingerprint.fusion import cold_start_fix
from server.estimation.floorplan import Walkable
from server.estimation.radio import multilaterate, range_and_std, range_from_rss
from server.estimation.tracking import (
    FloorTracker,
    LandmarkCorrector,
    Snap,
    apply_snap,
    make_tracker,
    selfcal,
    tracker_from_dict,
)
from server.estimation.tracking.base import TRACKERS, Tracker, fix_cov
from server.estimation.tracking.crowd import gate, make_crowd_point
from server.estimation.tracking.fixnoise import FixNoiseScale, student_t_factor
from server.estimation.tracking.shared_error import SharedFixError
from server.estimation.types import (
    Area,
    BatchOutcome,
    Beacon,
    CrowdCandidate,
    Estimate,
    Fix,
    FullState,
    InitialHeading,
    LateInput,
    LateInputs,
    NoFix,
    Scan,
    ScanNote,
    ScanResult,
    SiteMap,
    Step,
    TrackerFailure,
)

#: initial covariance (m²) when the phone gives a start position without one
DEFAULT_INITIAL_VAR_M2 = 1.0
#: 2: ``tracker_params`` added (a version-1 state loads with none)
STATE_VERSION = 2
#: innovation gate: a fix whose squared Mahalanobis distance from the estimate, under the
#: tracker's covariance plus the fix's, exceeds χ²(2 dof, 0.999) is an outlier (a fingerprint
#: match in the wrong place) and moves nothing
GATE_D2 = 13.82
#: after this many gated fixes in a row the tracker, not the fixes, may be lost (overconfident):
#: each further fix the gate would refuse first multiplies the tracker's covariance by
#: ``INFLATE_FACTOR`` and is tested again, so a lost tracker widens until the fixes pass
#: (weighted by the widened covariance) instead of one fix being taken blindly
MAX_GATED_IN_A_ROW = 3
INFLATE_FACTOR = 2.0
#: a self-calibrating tracker started on a fix (a session without an initial position) starts no
#: wider than this (m, per axis; `cold_start_cov`):
#: the model's covariance is its posterior's spread, far candidates included (σ ≈ 40 m on the
#: MSFT walks, whose first fix is 14 m off in mean, when this was chosen; ≈ 13 m since the
#: training step calibrates on every walk held out once), and a cloud that wide, clipped to the
#: walkable area, starts where walkable space is rather than at the fix (chosen on MSFT folds
#: 0–1 among 6, 8, 10, 12, 15, 20 m and ×0.05–0.25 of the fix's covariance; pf cold 13.1 → 8.8 m,
#: skpf 10.2 → 9.3, ekf 9.7 → 9.2 with the prior below; 15 rather than 10 m, which did as well
#: there, because a wrong first fix then weighs less against the later ones: the start's
#: variance is 0.56× a later fix's, not 0.25×; docs/msft-evaluation.md, "Cold start")
COLD_START_MAX_STD_M = 15.0
#: every other start from a fix (a seed form's first fix, any filter's restart on a confirmed floor
#: change) starts no wider than this (m, per axis): far wider than a fix's calibrated σ (≤ 40 m on
#: the MSFT walks), so such fixes start as given, but a start as wide as a degenerate fix is unsafe:
#: a path-loss model's fix from transmitters nearly in a line has σ ≈ 10⁵–10⁶ m across the line and
#: a nearly singular covariance, and a tracker started on one was sent 5–400 km away by the next (or
#: raised, ukf-xy); the multi-floor crowd benchmark's round 1 on seed 5 tracked at a 519 m mean
START_MAX_STD_M = 100.0
#: ... and its fixes' scale (``FixNoiseScale``) starts from this prior instead of 1: it has no
#: position but its fixes to learn their scatter from, while a wide model covariance makes it
#: follow them slowly (chosen on MSFT folds 0–1 among 0.15, 0.25, 0.35, 0.5; the known-start
#: sessions keep the prior 1; with the fixes at σ ≈ 13 m, 0.25 / 0.5 / 1 gave pf 8.6 / 9.2 / 10.2 m,
#: skpf 9.6 / 9.6 / 9.5, ekf 9.4 / 9.3 / 9.3 there). The prior applies to the trackers that learn their fix noise only.
COLD_FIX_SCALE_PRIOR = 0.25
#: ``FloorTracker`` follows one integer per floor: (building, level) packed as
#: building · FLOOR_KEY + level (levels lie within ±FLOOR_KEY/2), so a state stored before
#: buildings (building 0: the level itself) reads unchanged
FLOOR_KEY = 1000


def floor_key(building: int, level: int) -> int:
    return int(building) * FLOOR_KEY + int(level)


def building_level(key: int) -> tuple[int, int]:
    """The (building, level) of a ``floor_key``."""
    building = (int(key) + FLOOR_KEY // 2) // FLOOR_KEY
    return building, int(key) - building * FLOOR_KEY


class FixSource(Protocol):
    """Turns one scan into a fingerprint fix, restricted to ``near`` when given; raises
    ``NoFix`` (saying why) when the scan gives none."""

    def fix(self, scan: Scan, near: Area | None) -> Fix: ...


class SessionEstimator:
    """The whole per-session estimation state. ``tracker`` is None until the first fix
    of a session opened without an initial position."""

    def __init__(self, filter: str, seed: int, tracker_params: dict[str, Any] | None = None):
        self.filter = filter
        self.seed = int(seed)
        #: keyword arguments for the tracker this session starts (none: its defaults)
        self.tracker_params: dict[str, Any] = dict(tracker_params or {})
        self.tracker: Tracker | None = None
        self.floors: FloorTracker | None = None
        self.landmarks = LandmarkCorrector({})
        self.last_t: float | None = None
        self.estimate: Estimate | None = None
        #: a self-calibrating tracker's whole state at ``estimate`` (not stored with the session:
        #: with the track, for the smoother)
        self.full_state: FullState | None = None
        #: fixes refused by the innovation gate since the last accepted one
        self.gated_in_a_row = 0
        #: how much this session's fixes scatter against their own covariance (fixnoise.py)
        self.fix_noise = FixNoiseScale()
        #: what the tracker's covariance leaves out: the walk's fixes' shared error, a cold start's
        #: narrowed inputs (shared_error.py); added to every estimate's covariance
        self.shared_error = SharedFixError()
        #: the walking direction and its σ a session's ``initial`` gave (degrees, site frame), until its
        #: first step turns them into an observation of a self-calibrating tracker's heading bias
        self.initial_heading: InitialHeading | None = None
        #: the site's walls the tracker was last given (not stored: they come from the site)
        self._plan_walls: list | None = None
        #: diagnostics for offline evaluation (not stored): when a list, every gated fix
        #: appends (squared Mahalanobis distance before any inflation, accepted)
        self.innovations: list[tuple[float, bool]] | None = None
        #: called with the tracker, each estimate it makes and the tracker's own position covariance
        #: there (the estimate's less ``shared_error``'s excess): a replay's particle smoother; not stored
        self.on_record: Callable[[Tracker, Estimate, np.ndarray], None] | None = None

    # -- starting -----------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self.tracker is not None

    def start(self, mean, cov, floor: int, walls, t: float | None, source: str, building: int = 0,
              walkable: Walkable | None = None, heading: InitialHeading | None = None) -> Estimate:
        """A new tracker at (mean, cov) on that floor, with its walls and walkable area; its first
        estimate. ``heading``: the walker's direction there, known independently of the phone's
        compass, kept for the first step (``step``)."""
        self.initial_heading = heading
        cov = np.eye(2) * DEFAULT_INITIAL_VAR_M2 if cov is None else fix_cov(cov)
        self.tracker = make_tracker(self.filter, mean, cov, walls=walls, seed=self.seed, **self.tracker_params)
        self.tracker.set_walkable(walkable)
        self._plan_walls = walls
        self.floors = FloorTracker(floor_key(building, floor))
        return self._record(t, source)

    def _record(self, t: float | None, source: str, step: Step | None = None) -> Estimate:
        """The tracker's estimate now, and (``full_state``) a self-calibrating tracker's whole state.
        Where the floor has a walkable area the estimate's position is the walkable point nearest
        the tracker's mean (a walker is never inside a wall; the smoothed track does the same),
        while the tracker itself, and the stored state the smoother reads, keep their own mean."""
        assert self.tracker is not None and self.floors is not None
        building, level = building_level(self.floors.floor)
        mean = self.tracker.mean
        if self.tracker.walkable is not None:
            mean = self.tracker.walkable.nearest_inside(mean)[0]
        own = self.tracker.covariance
        reported = self.shared_error.reported(own) if self.shared_error.active else own
        self.estimate = Estimate.of(t, mean, reported, level, source, building)
        n = selfcal.N_AUG  # (the smoother's state: an EKF's walk offset is not smoothed)
        tr = self.tracker
        self.full_state = (FullState.of(tr.state_mean[:n], tr.state_covariance[:n, :n], step,
                                        None if step is None else tr.step_joint)
                           if isinstance(tr, selfcal.Calibrating) else None)
        if self.on_record is not None:
            self.on_record(self.tracker, self.estimate, own)
        return self.estimate

    def _considered(self, share: float | None = None, narrowed: bool = False) -> selfcal.Calibrating | None:
        """The tracker when this input moves ``shared_error``: a self-calibrating one that does not
        carry the walk's offset itself, once a fix has shared its error or been taken narrower than
        its measured covariance (or this one is)."""
        t = self.tracker
        if (isinstance(t, selfcal.Calibrating) and not t.models_walk_offset
                and (bool(share) or narrowed or self.shared_error.active)):
            return t
        return None

    def search_area(self) -> Area | None:
        """Where the tracker allows the fingerprint model to look (None: anywhere;
        ``Tracker.search_region``)."""
        return None if self.tracker is None else self.tracker.search_region()

    # -- a whole batch ----------------------------------------------------------------
    def apply_batch(
        self, steps: list[Step], scans: list[Scan], fixes: FixSource, site: SiteMap, *, crowdsourcing: bool = False,
    ) -> BatchOutcome:
        """Apply a batch in time order. Raises ``LateInputs`` (and changes nothing) when an
        input is older than the last applied one. A scan without a fix is skipped (its time
        still counts); a fix the innovation gate refuses is reported, and the scan's beacon
        ranges and landmarks still apply. With ``crowdsourcing``, tight estimates that agree
        with their scan's own fix become crowd candidates (never the cold-start scan: there
        the estimate *is* the fix). Raises ``TrackerFailure`` when the tracker fails numerically
        on an input (this estimator is then unusable: the caller keeps its stored state)."""
        ordered = time_order(steps, scans)
        if self.last_t is not None:
            late = [LateInput(kind, i, item.t) for kind, i, item in ordered if item.t < self.last_t]
            if late:
                raise LateInputs(late, self.last_t)
        try:
            return self._apply(ordered, fixes, site, crowdsourcing)
        except (np.linalg.LinAlgError, ArithmeticError) as exc:
            raise TrackerFailure(f"the {self.filter} tracker could not apply this batch's inputs "
                                 f"({type(exc).__name__}: {exc})") from exc

    def _apply(self, ordered: list[tuple[str, int, Step | Scan]], fixes: FixSource, site: SiteMap,
               crowdsourcing: bool) -> BatchOutcome:
        """`apply_batch` on inputs in time order, none late."""
        init_undated = self.estimate is not None and self.estimate.source == "init" and self.estimate.t is None
        estimates: list[Estimate] = []
        states: list[FullState | None] = []
        skipped: list[ScanNote] = []
        rejected: list[ScanNote] = []
        rejected_snaps: list[ScanNote] = []
        crowd: list[CrowdCandidate] = []
        applied_steps = applied_scans = 0
        for _, i, item in ordered:
            self._use_plan(site)
            if isinstance(item, Step):
                e = self.step(item)
                if e is not None:
                    applied_steps += 1
                    estimates.append(e)
                    states.append(self.full_state)
                continue
            try:
                fix = self._fix(item, fixes, site)
            except NoFix as why:
                skipped.append(ScanNote(i, str(why)))
                self.advance(item.t)
                continue
            cold = not self.started
            result = self.scan(item, fix, site)
            e = result.estimate
            applied_scans += 1
            estimates.append(e)
            states.append(self.full_state)
            if result.refused_snap is not None:
                rejected_snaps.append(ScanNote(i, result.refused_snap, applied_scans - 1))
            if result.refused_fix is not None:
                rejected.append(ScanNote(i, result.refused_fix, applied_scans - 1))
            elif crowdsourcing and not cold and gate([e.x, e.y], e.covariance, fix.mean, item.rss,
                                                     level=(e.building, e.floor), fix_level=(fix.building, fix.floor),
                                                     heard_level=strongest_level(item.rss, site.beacons)):
                point = make_crowd_point(e.x, e.y, e.floor, item.rss, e.building)
                crowd.append(CrowdCandidate(point, item))
        return BatchOutcome(
            estimates=tuple(estimates), estimate=self.estimate, applied_steps=applied_steps,
            applied_scans=applied_scans, skipped_scans=tuple(skipped), rejected_fixes=tuple(rejected),
            crowd=tuple(crowd), init_t=ordered[0][2].t if init_undated and ordered else None,
            states=tuple(states), rejected_snaps=tuple(rejected_snaps),
        )

    def _use_plan(self, site: SiteMap) -> None:
        """The floor plan comes from the site, not from the stored state: the tracker's floor's
        walls (set when they are not the ones it has), walkable area (a PF kills particles
        outside it; every estimate is reported inside it, ``_record``) and the grid its survey
        shows (a heading reference where the walls give none). A plan imported while a session is
        open applies at its next input."""
        if self.tracker is None or self.floors is None:
            return
        building, level = building_level(self.floors.floor)
        walls = site.walls_of(level, building)
        if walls is not self._plan_walls:
            self.tracker.set_walls(walls)
            self._plan_walls = walls
        self.tracker.set_walkable(site.walkable.get((building, level)))
        self.tracker.set_survey_grid(site.grids.get((building, level)))

    def _fix(self, scan: Scan, fixes: FixSource, site: SiteMap) -> Fix:
        """The scan's fix; a session's first fix is the cold-start fusion (DESIGN.md): fingerprint
        fix ⊕ multilateration from positioned transmitters, either alone when the other is missing."""
        if self.started:
            return fixes.fix(scan, self.search_area())
        fingerprint: Fix | None = None
        why: NoFix | None = None
        try:
            fingerprint = fixes.fix(scan, None)
        except NoFix as exc:
            why = exc
        ml = multilateration_fix(scan.rss, site.beacons, None if fingerprint is None else fingerprint.floor,
                                 building_hint=None if fingerprint is None else fingerprint.building)
        if fingerprint is None and ml is None:
            raise why if why is not None else NoFix("no fix")
        return cold_start_fix(fingerprint, ml)

    # -- single inputs --------------------------------------------------------------
    def advance(self, t: float) -> None:
        """Note an input at time ``t`` (applied or skipped); an initial position given without
        a time takes the time of the first input."""
        if self.estimate is not None and self.estimate.source == "init" and self.estimate.t is None:
            self.estimate = replace(self.estimate, t=float(t))
        self.last_t = t

    def step(self, step: Step) -> Estimate | None:
        """Predict with one step; None (step dropped) before the session has a position."""
        self.advance(step.t)
        if self.tracker is None:
            return None
        if self.initial_heading is not None:
            if isinstance(self.tracker, selfcal.Calibrating):  # (the seed forms carry no bias to tell)
                self.tracker.observe_heading(step, self.initial_heading.heading_deg, self.initial_heading.std_deg)
            self.initial_heading = None
        considered = self._considered()
        before = None if considered is None else considered.state_mean
        self.tracker.predict(step)
        if before is not None:
            self.shared_error.step(before, step)
        return self._record(step.t, "step", step)

    def scan(self, scan: Scan, fix: Fix, site: SiteMap) -> ScanResult:
        """Update with one scan's fix, beacon ranges and landmark snaps; start the session on
        its first fix. Returns the estimate and why the innovation gate refused the fix or the
        snap, if it did (a refused one moves nothing)."""
        self.advance(scan.t)
        if self.tracker is None or self.floors is None:
            walls = site.walls_of(fix.floor, fix.building)
            augmented = getattr(TRACKERS.get(self.filter), "augmented", False)
            if augmented:  # (seed forms: the fix as given, up to START_MAX_STD_M)
                self.fix_noise = FixNoiseScale(prior=COLD_FIX_SCALE_PRIOR)
            cov = cold_start_cov(fix.covariance, COLD_START_MAX_STD_M if augmented else START_MAX_STD_M)
            first = self.start(fix.mean, cov, fix.floor, walls, scan.t, "scan", fix.building,
                               site.walkable.get((fix.building, fix.floor)))
            if self._considered(fix.shared_share, narrowed=True) is not None:  # (the start's error is this fix's)
                self.shared_error.restart(fix_cov(fix.covariance), fix.shared_share, R_start=fix_cov(cov))
            return ScanResult(first)
        refused = None
        floor_before = self.floors.floor
        if self.floors.observe(floor_key(fix.building, fix.floor)):
            # A confirmed floor change (maybe into another building): its plan, restart from the fix there.
            self._use_plan(site)
            R_start = cold_start_cov(fix.covariance, START_MAX_STD_M)
            self.tracker.reset(fix.mean, R_start)
            scale = self.fix_noise.scale
            if self._considered(fix.shared_share, narrowed=scale > 1.0) is not None:
                self.shared_error.restart(fix_cov(fix.covariance) * max(scale, 1.0), fix.shared_share,
                                          R_start=R_start)
        elif floor_key(fix.building, fix.floor) == floor_before:
            refused = self._update(fix)
        # (a fix on another, not yet confirmed floor moves nothing)
        building, floor = building_level(self.floors.floor)
        if self.tracker.supports_range:
            for tx_id, rss in scan.rss.items():
                b = site.beacons.get(tx_id)
                if b is not None and b.tx_power_dbm is not None and b.path_loss_exponent is not None \
                        and b.on(building, floor):
                    self._range((b.x, b.y), *range_and_std(rss, b.tx_power_dbm, b.path_loss_exponent))
        self.landmarks.beacons = {
            k: (b.x, b.y) for k, b in site.beacons.items() if k.startswith("ble:") and b.on(building, floor)
        }
        refused_snap = None
        for snap in self.landmarks.observe(scan.rss)[:1]:
            refused_snap = self._snap(snap, building, floor)
        return ScanResult(self._record(scan.t, "scan"), refused, refused_snap)

    def _range(self, beacon_xy: tuple[float, float], range_m: float, std_m: float) -> None:
        """A beacon range, and what it does to ``shared_error`` when the tracker used it."""
        assert self.tracker is not None
        considered = self._considered()
        if considered is None:
            self.tracker.update_range(beacon_xy, range_m, std_m)
            return
        n = selfcal.N_AUG
        prior = np.array(considered.state_covariance, float)[:n, :n]
        if self.tracker.update_range(beacon_xy, range_m, std_m):
            self.shared_error.measured(prior, considered.state_covariance[:n, :n])

    def _snap(self, snap: Snap, building: int, floor: int) -> str | None:
        """A landmark snap. A self-calibrating tracker takes it as a measurement, N(beacon,
        snap_std²·I): refused by the fixes' gate (χ²(2, 0.999)) when the beacon is implausible under
        its estimate, else its fix update. A snap lands metres from the walker about as often as the
        tracker is metres off, so a reset that trusts it blindly lost more than it gave
        (docs/tracking-design.md, "Landmark snaps as gated measurements"). A seed form restarts on
        the beacon (``apply_snap``): its covariance does not model its drift, so the gate would refuse
        the snaps that rescue it. Returns why it refused the snap, if it did."""
        assert self.tracker is not None
        if not self.tracker.augmented:
            apply_snap(self.tracker, snap)
            return None
        fix = Fix(snap.x, snap.y, floor, snap.covariance, building=building, shared_share=0.0)
        d2 = self._d2(fix, snap.covariance)
        if d2 <= GATE_D2:
            self._take(fix, snap.covariance, snap.covariance)
            return None
        return self._outlier(f"landmark snap to {snap.beacon_id}", fix, d2)

    def _update(self, fix: Fix) -> str | None:
        """Update with the fix unless the innovation gate refuses it (then: why).

        A self-calibrating tracker (``Tracker.augmented``) first scales the fix's covariance by
        what this session has learned of its fixes' scatter (``fix_noise``; every fix, refused
        or not, then teaches it) and updates with Student-t weight (``fixnoise``). Covariance
        matching needs a tracker whose own covariance is honest: a seed form's is not (it
        does not model the PDR's bias), its innovations would blame the fixes for its drift
        and it would trust them ever less, so the seed forms (``-xy``, ``kf``, ``fkf``) take
        the fix as the model gives it. After ``MAX_GATED_IN_A_ROW`` refusals in a row, each
        fix the gate would refuse first grows the tracker's covariance by ``INFLATE_FACTOR``
        and is tested again, so a lost tracker is pulled back by fixes it has learned to
        trust less in itself."""
        assert self.tracker is not None
        R_own = fix_cov(fix.covariance)
        learns = self.tracker.augmented
        scale = self.fix_noise.scale if learns else 1.0
        R = R_own * scale
        fix = replace(fix, covariance=R)
        expected = self.tracker.fix_innovation(fix)
        d2 = expected.d2(R)
        if self.innovations is not None:
            self.innovations.append((d2, d2 <= GATE_D2))
        if learns:
            self.fix_noise.observe(expected.innovation, expected.covariance, expected.noise_share * R_own)
        if d2 > GATE_D2 and self.gated_in_a_row >= MAX_GATED_IN_A_ROW:
            self.tracker.inflate(INFLATE_FACTOR)
            d2 = self._d2(fix, R)
        if d2 <= GATE_D2:
            self.gated_in_a_row = 0
            t = student_t_factor(d2) if learns else 1.0
            self._take(fix, R_own * max(scale, 1.0), R * t, narrowed=scale * t < 1.0)
            return None
        self.gated_in_a_row += 1
        return self._outlier("fix", fix, d2)

    def _take(self, fix: Fix, R: np.ndarray, R_used: np.ndarray, narrowed: bool = False) -> None:
        """The tracker's update with an accepted fix of marginal covariance ``R`` (as the session
        measures its fixes), taken with ``R_used`` (``narrowed``: narrower than ``R``); and what it
        does to ``shared_error``."""
        assert self.tracker is not None
        considered = self._considered(fix.shared_share, narrowed)
        prior = None if considered is None else considered.state_covariance
        self.tracker.update(replace(fix, covariance=R_used))
        if prior is not None:
            n = selfcal.N_AUG
            self.shared_error.fix(prior[:n, :n], fix_cov(R), fix_cov(R_used), fix.shared_share)

    def _outlier(self, what: str, fix: Fix, d2: float) -> str:
        """Why the gate refused ``fix`` (a fingerprint fix or a landmark snap)."""
        assert self.tracker is not None
        distance = float(np.hypot(*(np.asarray(fix.mean, float) - self.tracker.mean)))
        return f"{what} {distance:.1f} m from the estimate is an outlier (squared Mahalanobis distance {d2:.1f} > {GATE_D2})"

    def _d2(self, fix: Fix, R: np.ndarray) -> float:
        """Squared Mahalanobis distance of the fix from what the tracker expects of it
        (``Tracker.fix_innovation``: P + R, or with the walk's fix offset)."""
        assert self.tracker is not None
        return self.tracker.fix_innovation(fix).d2(R)

    # -- persistence ----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "version": STATE_VERSION,
            "filter": self.filter,
            "seed": self.seed,
            "tracker_params": dict(self.tracker_params),
            "tracker": None if self.tracker is None else self.tracker.to_dict(walls=False),
            "floors": None if self.floors is None else self.floors.to_dict(),
            "landmarks": self.landmarks.to_dict(),
            "last_t": self.last_t,
            "estimate": None if self.estimate is None else self.estimate.to_dict(),
            "gated_in_a_row": self.gated_in_a_row,
            "fix_noise": self.fix_noise.to_list(),
            "shared_error": self.shared_error.to_dict(),
            **({} if (h := self.initial_heading) is None else {"initial_heading": [h.heading_deg, h.std_deg]}),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SessionEstimator:
        if d.get("version") not in (1, STATE_VERSION):
            raise ValueError(f"unsupported session state version {d.get('version')!r}")
        obj = cls(d["filter"], d["seed"], d.get("tracker_params"))  # version 1 has none
        obj.tracker = None if d["tracker"] is None else tracker_from_dict(d["tracker"])
        obj.floors = None if d["floors"] is None else FloorTracker.from_dict(d["floors"])
        obj.landmarks = LandmarkCorrector.from_dict(d["landmarks"])
        obj.last_t = d["last_t"]
        obj.estimate = None if d["estimate"] is None else Estimate.from_dict(d["estimate"])
        obj.gated_in_a_row = d.get("gated_in_a_row", 0)  # absent from states stored before the gate
        obj.fix_noise = FixNoiseScale.from_list(d.get("fix_noise"))  # absent from older states
        obj.shared_error = SharedFixError.from_dict(d.get("shared_error"))  # absent from older states
        heading = d.get("initial_heading")  # (only until the first step)
        obj.initial_heading = None if heading is None else InitialHeading(*map(float, heading))
        return obj


def cold_start_cov(cov, max_std_m: float = COLD_START_MAX_STD_M) -> np.ndarray:
    """A first fix's covariance for starting a session: its eigenvalues capped at ``max_std_m``²
    (the axes kept), so a fix whose model spreads it over the whole floor starts at the fix."""
    w, v = np.linalg.eigh(fix_cov(cov))
    return fix_cov((v * np.minimum(w, max_std_m**2)) @ v.T)


def time_order(steps: list[Step], scans: list[Scan]) -> list[tuple[str, int, Step | Scan]]:
    """Steps and scans merged by time (stable; at equal times steps come first)."""
    items: list[tuple[str, int, Step | Scan]] = [("step", i, s) for i, s in enumerate(steps)]
    items += [("scan", i, s) for i, s in enumerate(scans)]
    items.sort(key=lambda it: (it[2].t, 0 if it[0] == "step" else 1, it[1]))
    return items


def strongest_level(rss: dict[str, float], beacons: dict[str, Beacon]) -> tuple[int, int] | None:
    """(building, floor) of the strongest heard transmitter whose position has a floor; None when
    the scan hears none. A floor slab costs a signal 10–20 dB, so that transmitter is usually on
    the walker's floor: the floor a multilateration takes, and a check on a crowd point's floor."""
    heard = [(v, b.building or 0, b.floor) for k, v in rss.items()
             if (b := beacons.get(k)) is not None and b.floor is not None]
    if not heard:
        return None
    _, building, floor = max(heard, key=lambda h: h[0])
    return building, floor


def multilateration_fix(
    rss: dict[str, float],
    beacons: dict[str, Beacon],
    floor_hint: int | None = None,
    default_r0_dbm: float = -45.0,
    default_gamma: float = 2.5,
    max_anchors: int = 8,
    building_hint: int | None = None,
) -> Fix | None:
    """Least-squares multilateration from the heard transmitters with known positions
    (ranges by the path-loss model, each transmitter's own R0/γ where stored), on
    ``floor_hint`` (of ``building_hint``) or else the floor of the strongest heard
    transmitter that has one. None when no positioned transmitter is heard or the floor
    cannot be told."""
    heard = sorted(((v, beacons[k]) for k, v in rss.items() if k in beacons), key=lambda vb: -vb[0])
    floor, building = floor_hint, building_hint or 0
    if floor is None:
        strongest = strongest_level(rss, beacons)
        if strongest is not None:
            building, floor = strongest
    anchors = [(v, b) for v, b in heard if floor is not None and b.on(building, floor)][:max_anchors]
    if floor is None or not anchors:
        return None
    xy = np.array([[b.x, b.y] for _, b in anchors])
    ranges = np.array([
        range_from_rss(v, default_r0_dbm if b.tx_power_dbm is None else b.tx_power_dbm,
                       default_gamma if b.path_loss_exponent is None else b.path_loss_exponent)
        for v, b in anchors
    ])
    mean, cov = multilaterate(xy, ranges)
    if not np.all(np.isfinite(mean)):
        return None
    return Fix(float(mean[0]), float(mean[1]), int(floor), fix_cov(cov), building=building)
