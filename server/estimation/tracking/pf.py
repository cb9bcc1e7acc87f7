"""PF: bootstrap particle filter (1,000 particles, systematic resampling, walls kill).

``pf`` is the self-calibrating form: each particle also carries its own heading bias and
step scale ([x, y, b, s], see ``selfcal``), which follow their random walks, so the
particles that survive the fixes are those whose calibration explains the walk.
``pf-xy`` is the two-state seed form described here.

Prediction samples each particle's own step: d_i ~ N(d, σd²), h_i ~ N(h, σh²), plus a
small isotropic jitter (q m² per step). A particle whose move crosses a wall, or that ends
outside the floor's walkable area when the session gave one (``set_walkable``, from the
site's floor plan; not stored, the session sets it before every input), dies (weight 0)
and the set is resampled at once, so no particle survives on the far side of a wall or
inside an obstacle. With ``resample_kills=0`` the dead keep weight 0 and the set is
resampled only when N_eff < resample_threshold·N, as after a fix: fewer resamplings leave
the cloud less impoverished (on the ``stress`` scenarios of benchmarks/scenario_family.py,
a PDR far worse than the held-out one, a 1.73 m mean instead of 2.88 and 0.7 % of the
estimates with a NEES above 50 instead of 4 %), but it did not win on the MSFT walks
(docs/msft-evaluation.md), so the default stays 1.

If every particle would die (the plan disagrees with the walker, or the PDR drove the
whole cloud into a wall): with a walkable area the cloud is redrawn around the last good
estimate — positions from N(m, P + d²·I), m and P the estimate before the step and d the
step length, keeping only draws inside the walkable area (the calibration columns
resampled from the old particles by weight); without one, or when no draw lands inside,
the step is applied without the test rather than losing the track.
A step that leaves survivors whose effective count is below ``min_survivors`` (100) would leave
a cloud of copies of a few points, with a covariance of ≈ 0 however far the walker is: the
resampled particles' positions then move by the regularised PF's kernel (Silverman's bandwidth
for that count, over the cloud's spread before the kill), each to a draw that crosses no wall
and ends walkable (``_spread_survivors``).
Many walls (a real plan) are tested through ``floorplan.WallIndex``.
Update multiplies the weights by the Gaussian likelihood N(z; x_i, R), R =
fix.covariance, and resamples when N_eff < resample_threshold·N. A beacon range weighs
in log-range (``measurements.log_range``: the path-loss model's error is log-normal), so a
strong reading of a far beacon does not leave a single particle alive.

Without a plan the self-calibrating ``pf`` then makes up half of what its cloud's covariance falls
short of a Kalman update of the cloud's own moments (``kalman_floor``, ``_keep_spread``):
reweighting alone narrows it faster than the measurements' information does.

With ``min_particles`` below ``n_particles`` the particle count adapts (KLD-sampling,
``resampling.kld_count``): each resampling draws as many particles as the cloud's spread
needs, between the two; equal values (the default: ``min_particles`` is ``n_particles`` unless
given) keep a fixed count; a reset starts with ``n_particles``.
Randomness comes from the tracker's own PCG64 generator, stored in ``to_dict()`` with
the particles and weights packed a byte per number (``packed``): each column on a grid of
256 values spanning the cloud (resolution ≈ 0.8 % of its spread; refitted whenever the
values change), the weights as their ratio to the largest on a log scale (±2.2 %), deflated
and in base85: ≈ 5.8 kB of text for 1,000 particles [x, y, b, s] and their weights (4.7 kB
after a resampling, when the weights are uniform; 8.8 and 7.7 kB with the shared error's u₁,
u₂), against 16 kB as float16 offsets and float32 weights in base64 (the session's whole
stored state per batch: 8.2 kB against 17 kB on the tune scenarios of
benchmarks/scenario_family.py, the same error and NEES; 9.9 kB with u). The filter
holds exactly those values (``_quantize`` after every change; a step's new positions are
rounded before the walls judge them, as are the draws of a redraw), so a restored filter
continues exactly as the one that was stored.
"""

from __future__ import annotations

import math

import numpy as np

from server.estimation import floorplan  # (a module: floorplan imports tracking.geometry)
from server.estimation.tracking import selfcal
from server.estimation.tracking.base import Tracker, as_cov, as_mean, fix_cov, register, symmetric
from server.estimation.tracking.geometry import crosses_walls, on_wrong_side
from server.estimation.tracking.measurements import (
    MIN_LOG_RANGE_M,
    log_range,
    log_range_H,
    log_range_h,
    parse_on_wall,
    range_usable,
)
from server.estimation.tracking.packed import (
    fit_grid,
    grid_of,
    on_grid,
    pack,
    pack_grid,
    pack_weights,
    snap,
    unpack,
    unpack_weights,
    weights_as_stored,
)
from server.estimation.tracking.resampling import effective_sample_size, kld_count, systematic_resample
from server.estimation.tracking.rng import make_rng, rng_from_state, rng_state
from server.estimation.types import Area, Fix, Step, StepJoint

#: KLD-sampling (``min_particles`` < ``n_particles``) is off by default. Chosen on the tune
#: scenarios of benchmarks/scenario_family.py (ε = 0.15, bins 1 m, at least 100: 6–8 kB per
#: stored state instead of 28 kB with the float32 particles of then, error within 5 % of a
#: fixed 1,000 particles'), it then cost
#: 27 % more error than PF-1000 on the held-out scenarios with wknn fixes (2.74 against 2.16 m;
#: +3–4 % with knn and unbiased fixes): small clouds collapse onto a wrong fix. The default
#: went back to a fixed 1,000 after that held-out run: ``min_particles`` defaults to
#: ``n_particles``.
KLD_BIN_M = 1.0
KLD_EPSILON = 0.15

#: below this effective count of a step's survivors (of 1,000) the walls' kill is followed by a
#: regularised spread (``_spread_survivors``; 0 = off). 100 was chosen over 20 and 50 on the tune and
#: stress scenarios of benchmarks/scenario_family.py with the loop's plan (stress: estimates above
#: NEES 10³ 194 → 135, error −2.5 %; tune never fires), then reported under a rule written first:
#: held-out draw 400–415 NEES mean 5·10⁵ → 3.85 (error −1.2 %), draws 416–447 the same to the digit,
#: MSFT folds 2–3 −0.3 % (docs/tracking-design.md, "A PF cloud that walls cut to a few survivors").
MIN_SURVIVORS = 100.0

#: the share of a fix's variance its walk's fixes share, and that error's correlation length
#: (steps): ``ParticleFilterTracker``; off by default (a session sets it through its
#: ``filter_params``). ρ = 0.35 over 20 steps was chosen from {0.1, 0.2, 0.35} × {20, 50, 100} on
#: the tune and stress scenarios of benchmarks/scenario_family.py with the loop's plan and the MSFT
#: walks' folds 0–1 (mean −16 % against ρ = 0), then lost on the reporting folds 2–3 (2.49 → 2.65
#: m over two seed salts): on walks whose compass was 45° off it explained the heading's error as
#: the fixes' and lost the track (docs/msft-evaluation.md, "The fixes' shared error in the PF").
FIX_BIAS_SHARE = 0.0
FIX_BIAS_STEPS = 20.0
#: with the fixes' shared error on, the probability per step that a particle's hypothesis about the
#: fixes flips (``fix_bias_switch``; 0: every particle takes the share ρ): the session learns whether
#: its walk's fixes share an error (``ParticleFilterTracker``, "learned per session")
FIX_BIAS_SWITCH = 0.0

#: the building's grid per straight run as a likelihood of each particle's heading bias
#: (``ParticleFilterTracker._observe_grid``; σ in degrees, 0 = off). Without a plan: the survey's
#: grid, the likelihood in two parts (``GRID_ON_SHARE``), the cloud kept as wide as a Kalman update by
#: it (``kalman_floor``); chosen on MSFT folds 0–1 and the tune and stress splits (−5.3 %), reported on
#: MSFT folds 2–3 (−13.5 %, NEES 1.5–3.4 → 2.0–3.2) and held-out draw 592–607 (1.33 → 1.13 m, NEES
#: 1.99 → 1.65): docs/msft-evaluation.md, "The survey's grid in the PF on a floor without a plan".
#: With a plan (``GRID_PLAN``): the walls' grid, the same two parts, σ widened by the run's own
#: heading noise (there is no Kalman floor there); chosen on MSFT folds 0–3 and held-out draw 608–623
#: (in-sample: folds 0–1 −4.8 %, 2–3 −2.5 %), reported on held-out draw 624–639 (knn fixes 0.81 →
#: 0.77 m, Gaussian 0.66 → 0.64; NEES 1.11 / 1.84): "The walls' grid in the PF with a plan".
GRID_SIGMA_DEG = selfcal.GRID_SIGMA_DEG
#: 1 (default): observe the grid on a floor with a plan too (the walls' grid); 0: only without one
GRID_PLAN = 1.0
#: the share π of straight runs that follow the grid; the rest are taken as spread evenly over its
#: 90°, so a particle whose bias puts a run off the grid keeps (1 − π)/90° of weight instead of none.
#: 0.6: what the MSFT site-1 fold maps' survey walks show (their straight runs, 3 moves within 10°:
#: π 0.53–0.66 with σ 3.0–3.3° about the grid; measured on the maps, before any tracking run)
GRID_ON_SHARE = 0.6

#: the share κ of a Kalman update's spread the PF's cloud keeps after a fix, a beacon range or a grid run,
#: without a plan (``ParticleFilterTracker._keep_spread``). 0.5 was chosen over 1 on the tune and
#: stress scenarios of benchmarks/scenario_family.py and the MSFT walks' folds 0–1 without the plan
#: (stress 4.60 → 3.85 m, NEES 11.6 → 5.0; tune 0.91 both; MSFT +2.3 %), then reported against 0
#: under a rule written first: held-out draws 0–15 and 64–79 (wknn, knn fixes) −5…−7 % error with
#: NEES 3.1–6.2 → 2.4–3.2, the unrun draw 96–111 +1 % / +3 % with NEES 1.7 / 2.1 → 1.6 / 1.9, MSFT
#: folds 2–3 −4 % with NEES 4.6 → 3.3 (docs/msft-evaluation.md, "The PF kept as wide as a Kalman update").
KALMAN_FLOOR = 0.5
#: χ²'s 99 % point by degrees of freedom: a measurement this far from the estimate (under its
#: innovation covariance) restores the whole calibration spread (``kalman_floor``)
CHI2_99 = {1: 6.63, 2: 9.21}


def weighted_covariance(points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Σ wᵢ (pᵢ − m)(pᵢ − m)ᵀ about the weighted mean m = Σ wᵢ pᵢ of the rows ``points``."""
    diff = points - weights @ points
    return (diff * weights[:, None]).T @ diff


def gaussian_loglik(points: np.ndarray, z, R: np.ndarray) -> np.ndarray:
    """log N(z; pᵢ, R) of each row pᵢ of ``points``, up to a constant (−½ of the Mahalanobis distance²)."""
    diff = points - np.asarray(z, float)
    return -0.5 * np.einsum("ij,jk,ik->i", diff, np.linalg.inv(R), diff)


@register
class ParticleFilterXYTracker(Tracker):
    name = "pf-xy"
    supports_range = True
    #: columns of a particle (2: [x, y]; 4 with the calibration)
    dim: int = 2
    particles: np.ndarray  # (n, dim), set by reset() and _load_state()
    _grid: tuple[np.ndarray, np.ndarray] | None  # the particles' grid per column (lo, step; None: float32 values)
    weights: np.ndarray  # (n,), sum 1
    #: a replay's record of descent (``particle_smoother``): for each particle, the row of the cloud at
    #: the last ``take_lineage`` it descends from, −1 for one drawn anew; None (the live filter) keeps none
    lineage: np.ndarray | None = None

    def __init__(self, initial_mean, initial_cov, walls=None, seed=None, **params):
        self._configure(walls, seed, **params)
        self.rng = make_rng(seed)
        self.reset(initial_mean, initial_cov)

    @classmethod
    def _restore(cls, state: dict, walls, params: dict) -> Tracker:
        """Configured and loaded without first drawing the particles and the generator that
        loading replaces (two thirds of a restore's cost)."""
        obj = cls.__new__(cls)
        obj._configure(walls, None, **params)
        obj._load_state(state)
        return obj

    def _configure(
        self,
        walls,
        seed,
        *,
        n_particles: int = 1000,
        q: float = 0.01,
        resample_threshold: float = 0.5,
        max_range_m: float = 3.0,
        min_particles: int | None = None,
        kld_bin_m: float = KLD_BIN_M,
        kld_epsilon: float = KLD_EPSILON,
        resample_kills: int = 1,
        min_survivors: float = MIN_SURVIVORS,
    ) -> None:
        """Everything but the particles and the generator: parameters, floor plan."""
        Tracker.__init__(self, None, None, walls=walls, seed=seed)
        if not min_survivors >= 0.0:
            raise ValueError("min_survivors must be at least 0")
        if n_particles < 2:
            raise ValueError("n_particles must be at least 2")
        if min_particles is None:
            min_particles = n_particles
        if not 2 <= min_particles <= n_particles:
            raise ValueError("min_particles must be between 2 and n_particles")
        if kld_bin_m <= 0 or kld_epsilon <= 0:
            raise ValueError("kld_bin_m and kld_epsilon must be positive")
        self.params = {
            "n_particles": int(n_particles),
            "min_particles": int(min_particles),
            "kld_bin_m": float(kld_bin_m),
            "kld_epsilon": float(kld_epsilon),
            "q": float(q),
            "resample_threshold": float(resample_threshold),
            "max_range_m": float(max_range_m),
            "resample_kills": int(resample_kills),
            "min_survivors": float(min_survivors),
        }
        self._grid = None
        self._wall_index: floorplan.WallIndex | None = None

    # -- filter -------------------------------------------------------------------
    def predict(self, step: Step) -> None:
        n = len(self.particles)
        d = step.length_m + step.length_std_m * self.rng.standard_normal(n)
        h = math.radians(step.heading_deg) + math.radians(step.heading_std_deg) * self.rng.standard_normal(n)
        move = np.column_stack((d * np.sin(h), d * np.cos(h)))
        move += math.sqrt(self.params["q"]) * self.rng.standard_normal((n, 2))
        self._settle(self.particles + move, step.length_m)

    def update(self, fix: Fix) -> None:
        self._reweight(self._fix_loglik(fix))

    def _fix_loglik(self, fix: Fix) -> np.ndarray:
        """Each particle's log-likelihood of ``fix`` (up to a constant): N(z; x_i, R)."""
        return gaussian_loglik(self.particles[:, :2], fix.mean, fix_cov(fix.covariance))

    def update_range(self, beacon_xy, range_m: float, range_std_m: float, on_wall=None) -> bool:
        if not range_usable(range_m, range_std_m, self.params["max_range_m"]):
            return False
        return self._reweight(self._range_loglik(beacon_xy, range_m, range_std_m, on_wall))

    def _range_loglik(self, beacon_xy, range_m: float, range_std_m: float, on_wall) -> np.ndarray:
        """Each particle's log-likelihood of a usable beacon range (in log-range; −∞ on the wrong
        side of the beacon's wall)."""
        beacon = np.asarray(beacon_xy, float).reshape(2)
        constraint = parse_on_wall(on_wall, self.mean)
        dist = np.hypot(self.particles[:, 0] - beacon[0], self.particles[:, 1] - beacon[1])
        z, sigma = log_range(range_m, range_std_m)
        loglik = -0.5 * ((np.log(np.maximum(dist, MIN_LOG_RANGE_M)) - z) / sigma) ** 2
        if constraint is not None:
            loglik = np.where(on_wrong_side(self.particles[:, :2], constraint.wall, constraint.side), -np.inf, loglik)
        return loglik

    # -- the floor plan -----------------------------------------------------------------
    def set_walls(self, walls) -> None:
        super().set_walls(walls)
        self._wall_index = None

    def _crosses(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        if len(self.walls) < floorplan.INDEX_FROM_WALLS:
            return crosses_walls(start, end, self.walls)
        if self._wall_index is None:
            self._wall_index = floorplan.WallIndex(self.walls)
        return self._wall_index.crosses(start, end)

    def _settle(self, moved: np.ndarray, step_m: float) -> None:
        """Move the particles to ``moved`` (same columns), killing those whose move crosses a
        wall or ends outside the walkable area; the rule when all would die is the module's.
        The moved particles are on their grid already (rounded before the walls judged them; a
        resampling only picks rows of them), so only a redraw's need rounding again; the weights
        are as stored whenever they changed (a kill renormalises them, a resampling makes them
        uniform)."""
        if self._move(moved, step_m):
            self._quantize()

    def _move(self, moved: np.ndarray, step_m: float) -> bool:
        """``_settle``'s move; True when the particles were redrawn."""
        old = self.particles
        moved = self._round(moved, refit=True)  # walls judge the positions the filter keeps
        dead = self._crosses(old[:, :2], moved[:, :2])
        if self.walkable is not None:
            dead |= ~self.walkable.contains(moved[:, :2])
        self.particles = moved
        if not dead.any():
            return False
        if not dead.all():
            p = self.params
            alive = np.where(dead, 0.0, self.weights)
            alive /= alive.sum()
            survivors = effective_sample_size(alive)
            if survivors < p["min_survivors"]:
                spread = symmetric(weighted_covariance(moved[:, :2], self.weights))  # (the weights before the kill)
                self.weights = alive
                self._resample()
                return self._spread_survivors(spread, survivors)
            self.weights = alive
            if p["resample_kills"] or survivors < p["resample_threshold"] * len(moved):
                self._resample()
            else:
                self.weights = weights_as_stored(self.weights)
            return False
        if self.walkable is not None:
            redrawn = self._redraw(old, step_m)
            if redrawn is not None:
                self.particles = redrawn
                self.weights = np.full(len(redrawn), 1.0 / len(redrawn))
                return True
        return False

    def _spread_survivors(self, P: np.ndarray, survivors: float, tries: int = 4) -> bool:
        """Move each (resampled) particle's position by a kernel N(0, h²·P), the regularised PF's
        Silverman bandwidth h = (4/((d + 2)·n_s))^(1/(d+4)) for d = 2 and n_s ``survivors``, P the
        cloud's spread before the walls cut it: the first of ``tries`` draws whose move crosses no
        wall and ends walkable, judged on the grid they are stored on; a particle with none takes
        another's accepted draw. False (the cloud as it is) when no draw is accepted."""
        n = len(self.particles)
        h2 = (1.0 / max(survivors, 1.0)) ** (1.0 / 3.0)
        L = np.linalg.cholesky(h2 * P + 1e-9 * np.eye(2))
        start = np.repeat(self.particles[:, :2], tries, axis=0)
        draws = start + self.rng.standard_normal((tries * n, 2)) @ L.T
        grid = fit_grid(draws)
        draws = snap(draws, *grid)
        ok = ~self._crosses(start, draws)
        if self.walkable is not None:
            ok &= self.walkable.contains(draws)
        ok = ok.reshape(n, tries)
        if not ok.any():
            return False
        pick = draws.reshape(n, tries, 2)[np.arange(n), ok.argmax(axis=1)]
        none = ~ok.any(axis=1)
        if none.any():
            accepted = pick[~none]
            pick[none] = accepted[self.rng.integers(len(accepted), size=int(none.sum()))]
        self.particles[:, :2] = pick
        self._keep_position_grid(grid)
        return True

    def _keep_position_grid(self, grid: tuple[np.ndarray, np.ndarray]) -> None:
        """New positions drawn on ``grid`` (x, y) keep it; the other columns keep theirs."""
        if self._grid is not None:
            self._grid = (np.concatenate((grid[0], self._grid[0][2:])), np.concatenate((grid[1], self._grid[1][2:])))

    def _redraw(self, old: np.ndarray, step_m: float, tries: int = 4) -> np.ndarray | None:
        """n particles around the weighted mean of ``old`` (spread its covariance + step_m²·I),
        only inside the walkable area; None when no draw lands there."""
        assert self.walkable is not None
        n = len(old)
        m = self.weights @ old[:, :2]
        P = weighted_covariance(old[:, :2], self.weights) + (step_m**2 + self.params["q"]) * np.eye(2)
        L = np.linalg.cholesky(symmetric(P) + 1e-9 * np.eye(2))
        draws = m + self.rng.standard_normal((tries * n, 2)) @ L.T
        grid = fit_grid(draws)  # judged as they will be kept: on a grid of their own (``_round``)
        draws = snap(draws, *grid)
        inside = draws[self.walkable.contains(draws)]
        if len(inside) == 0:
            return None
        pick = inside[:n] if len(inside) >= n else inside[self.rng.integers(len(inside), size=n)]
        rows = systematic_resample(self.weights, float(self.rng.random()))
        self._descend(rows)
        out = old[rows].copy()
        out[:, :2] = pick
        self._keep_position_grid(grid)
        return out

    def _reweight(self, loglik: np.ndarray) -> bool:
        with np.errstate(divide="ignore"):
            logw = np.log(self.weights) + loglik
        top = np.max(logw)
        if not np.isfinite(top):
            return False  # the measurement is impossible for every particle: ignore it
        w = np.exp(logw - top)
        self.weights = w / w.sum()
        if effective_sample_size(self.weights) < self.params["resample_threshold"] * len(self.weights):
            self._resample()
        self.weights = weights_as_stored(self.weights)  # (the particles did not move)
        return True

    def _resample(self) -> None:
        """Systematic resampling to the count the cloud needs (KLD-sampling; a fixed count when
        ``min_particles`` is ``n_particles``). The particles picked are on their grid already."""
        p = self.params
        n = p["n_particles"]
        if p["min_particles"] < n:  # the weighted cloud's bins, approximated by the particles that carry weight
            n = kld_count(self.particles[self.weights > 0, :2], p["kld_bin_m"], p["kld_epsilon"],
                          p["min_particles"], n)
        idx = systematic_resample(self.weights, float(self.rng.random()), n)
        self._descend(idx)
        self.particles = np.asfortranarray(self.particles[idx])
        self.weights = weights_as_stored(np.full(n, 1.0 / n))

    def _quantize(self) -> None:
        """Particles and weights as stored (``packed``: a byte each): what ``to_dict`` stores
        is then exactly what the filter holds."""
        self.particles = self._round(self.particles, refit=False)
        self.weights = weights_as_stored(self.weights)

    def _round(self, points: np.ndarray, refit: bool | np.ndarray) -> np.ndarray:
        """Rows of particles as stored: each column on a grid of 256 values (``packed``), the
        one it is on already unless ``refit`` (then rounding again changes nothing), else one
        fitted to its values; ``refit`` a mask of columns: those get a grid fitted to their
        values, the others keep theirs (their values are on it: the caller did not change them),
        without testing each value; float32 values when a value is not finite. Column-major (a
        particle's columns are reduced and moved one at a time: 10× faster than row-major)."""
        points = np.asfortranarray(points)
        if not np.all(np.isfinite(points)):
            self._grid = None
            return points.astype(np.float32).astype(float)
        if refit is True or self._grid is None or len(self._grid[0]) != points.shape[1]:
            lo, step = fit_grid(points)
        else:
            lo, step = self._grid
            keep = on_grid(points, lo, step) if refit is False else ~np.asarray(refit, bool)
            if keep.all():
                return points  # on the grid already: rounding again changes nothing
            fit_lo, fit_step = fit_grid(points)
            lo, step = np.where(keep, lo, fit_lo), np.where(keep, step, fit_step)
        self._grid = (lo, step)
        return snap(points, lo, step)

    # -- descent (a replay's particle smoother) -------------------------------------------------
    def _descend(self, rows: np.ndarray | None) -> None:
        """The particles are now ``rows`` of the previous ones (None: positions drawn anew)."""
        if self.lineage is not None:
            self.lineage = np.full(self.params["n_particles"], -1) if rows is None else self.lineage[rows]

    def take_lineage(self) -> np.ndarray:
        """Each particle's row in the cloud at the previous call (−1: drawn anew since), and from now
        on record descent from the cloud as it is (the first call: every particle its own row)."""
        rows = np.arange(len(self.particles)) if self.lineage is None else self.lineage
        self.lineage = np.arange(len(self.particles))
        return rows

    # -- estimate -----------------------------------------------------------------
    @property
    def mean(self) -> np.ndarray:
        return self.weights @ self.particles[:, :2]

    @property
    def covariance(self) -> np.ndarray:
        return symmetric(weighted_covariance(self.particles[:, :2], self.weights)) + 1e-9 * np.eye(2)

    def reset(self, mean, cov) -> None:
        n = self.params["n_particles"]
        L = np.linalg.cholesky(as_cov(cov))
        self.particles = as_mean(mean) + self.rng.standard_normal((n, 2)) @ L.T
        self.weights = np.full(n, 1.0 / n)
        self._descend(None)
        self._quantize()

    def inflate(self, factor: float) -> None:
        """Spread the particles about their mean by √factor (every column), weights kept."""
        m = self.weights @ self.particles
        self.particles = m + math.sqrt(float(factor)) * (self.particles - m)
        self._quantize()

    # -- persistence --------------------------------------------------------------
    def _state(self) -> dict:
        return {
            "mean": self.mean.tolist(),
            "cov": self.covariance.tolist(),
            "particles": pack(self.particles) if self._grid is None else pack_grid(self.particles, *self._grid),
            "weights": pack_weights(self.weights),  # None: uniform (after a resampling)
            "rng": rng_state(self.rng),
        }

    def _load_state(self, state: dict) -> None:
        particles = unpack(state["particles"])
        n = particles.size // self.dim
        if not 2 <= n <= self.params["n_particles"] or particles.size != n * self.dim:
            raise ValueError(f"stored particles do not fit {self.params['n_particles']} × {self.dim}")
        self.particles = np.asfortranarray(particles.reshape(n, self.dim))
        self.weights = unpack_weights(state["weights"], n)
        self.rng = rng_from_state(state["rng"])
        # as stored, not rounded again: the grid was fitted to the values before their rounding
        self._grid = grid_of(state["particles"])
        if self._grid is None:  # float32 values, or an older form (held as stored from now on)
            self._quantize()


@register
class ParticleFilterTracker(selfcal.Calibrating, ParticleFilterXYTracker):
    """Self-calibrating PF: particles [x, y, b, s], and [u₁, u₂] with a floor plan.

    Prediction per particle: b_i += N(0, σb²), s_i += N(0, σs²) (kept in range), then its
    step d_i = s_i·(d + σd·ε), h_i = h + b_i + σh·ε, plus the q jitter; walls and the walkable
    area kill as in the seed form. At the start b_i ~ N(0, σb0²), s_i ~ N(1, σs0²). A ``reset`` (snap, floor
    change) redraws the positions and keeps each particle's calibration.

    **The fixes' shared error** (``fix_bias_share`` ρ > 0, columns u): a walk's fingerprint
    fixes are biased together (the same wrong corridor for a while), and fused as independent
    they drag the cloud. Each particle carries a unit-variance Gauss–Markov u (u ← φ·u +
    √(1 − φ²)·ε per step, φ = exp(−1/``fix_bias_steps``)), and a fix z with covariance R is
    weighed as z ~ N(p + √ρ·L·u, (1 − ρ)·R), L Lᵀ = R: a share ρ of each fix's variance is a
    bias the walk's fixes share, in units of the fix's own covariance (so one ρ serves a site
    whose fixes are 2 m off and one whose fixes are 12 m off). Only where the floor has a plan
    (walls or a walkable area): the walls are what tell a fix bias from a heading bias; without
    them both explain the same innovations and the tracker lets the fixes' "bias" absorb the
    walk's drift (docs/msft-evaluation.md, "A fix-bias state in the EKF"), so u is then left
    alone and fixes weigh as N(p, R). A state stored before this (four columns) loads with
    ρ = 0 and goes on as it started.

    **Learned per session** (``fix_bias_switch`` π > 0, column k): one ρ cannot serve both a walk
    whose fixes are biased together and one whose fixes are not (the first needs ρ, the second is
    made underconfident by it). So each particle also carries a hypothesis kᵢ ∈ {0, 1} (half of
    each at the start) and weighs a fix as N(z; p + √(ρkᵢ)·L·u, (1 − ρkᵢ)·R): the fixes' own
    sequence selects the hypothesis (correlated innovations favour k = 1, independent ones k = 0),
    and kᵢ flips with probability π per step (a jump between the two models, as in an IMM), so
    neither hypothesis dies out for good. The weighted mean of ρk is the session's learned share.

    **The cloud's spread without a plan** (``kalman_floor`` κ, default 0.5): after an accepted
    fix, a beacon range or an observation of the grid, the particles get N(0, D), D the κ-share of what a Kalman update of
    the cloud's mean and covariance would keep beyond the reweighted cloud (``_keep_spread``).

    **The building's grid** (``grid_sigma_deg``, 3° by default, ``GRID_SIGMA_DEG``): every
    ``grid_steps`` of a straight run the particles are weighed by their bias's fit to the walls'
    grid, else the survey's (``_observe_grid``), the Gaussian filters' heading reference as a
    likelihood; ``grid_plan`` 0 leaves it out on a floor with a plan."""

    name = "pf"
    dim = 4  # 6 with the fixes' shared error (``fix_bias_share`` > 0), 7 with it learned (``fix_bias_switch`` > 0)

    def _configure(
        self,
        walls,
        seed,
        *,
        bias0_std_deg: float = selfcal.BIAS0_STD_DEG,
        bias_walk_deg: float = selfcal.BIAS_WALK_DEG,
        scale0_std: float = selfcal.SCALE0_STD,
        scale_walk: float = selfcal.SCALE_WALK,
        fix_bias_share: float = FIX_BIAS_SHARE,
        fix_bias_steps: float = FIX_BIAS_STEPS,
        fix_bias_switch: float = FIX_BIAS_SWITCH,
        kalman_floor: float = KALMAN_FLOOR,
        grid_sigma_deg: float = GRID_SIGMA_DEG,
        grid_gate_deg: float = selfcal.GRID_GATE_DEG,
        grid_steps: float = selfcal.GRID_STEPS,
        grid_plan: float = GRID_PLAN,
        grid_on_share: float = GRID_ON_SHARE,
        search_sigmas: float = selfcal.SEARCH_SIGMAS,
        search_margin_m: float = selfcal.SEARCH_MARGIN_M,
        **pf_params,
    ) -> None:
        """The seed form's configuration (``pf_params``) plus the calibration's random walks,
        the fixes' shared error, the building's grid and where the fingerprint model may look."""
        self._cal = selfcal.calibration_params(bias0_std_deg, bias_walk_deg, scale0_std, scale_walk)
        if not 0.0 <= fix_bias_share < 1.0:
            raise ValueError("fix_bias_share must be at least 0 and below 1")
        if not fix_bias_steps >= 1.0:
            raise ValueError("fix_bias_steps must be at least 1")
        if not 0.0 <= fix_bias_switch <= 0.5:
            raise ValueError("fix_bias_switch must be between 0 and 0.5")
        if not 0.0 <= kalman_floor <= 1.0:
            raise ValueError("kalman_floor must be between 0 and 1")
        if grid_plan not in (0, 1):
            raise ValueError("grid_plan must be 0 or 1")
        if not 0.0 < grid_on_share <= 1.0:
            raise ValueError("grid_on_share must be above 0 and at most 1")
        super()._configure(walls, seed, **pf_params)
        self.params.update(self._cal, kalman_floor=float(kalman_floor), grid_plan=float(grid_plan),
                           grid_on_share=float(grid_on_share),
                           **selfcal.grid_params(grid_sigma_deg, grid_gate_deg, grid_steps),
                           **selfcal.search_params(search_sigmas, search_margin_m))
        self._set_fix_bias(float(fix_bias_share), float(fix_bias_steps), float(fix_bias_switch))

    def _set_fix_bias(self, share: float, steps: float, switch: float) -> None:
        self.params.update(fix_bias_share=share, fix_bias_steps=steps, fix_bias_switch=switch)
        self.dim = 4 if share <= 0 else 6 if switch <= 0 else 7

    def _has_plan(self) -> bool:
        return len(self.walls) > 0 or self.walkable is not None

    def search_region(self) -> Area | None:
        """``Calibrating.search_region`` on a floor without a plan; with one, anywhere: walls narrow
        the cloud, and a cloud that narrow fed the best matches near itself confirms itself (one
        stress walk of twelve followed a wrong corridor 15 m off at NEES 10³; docs/tracking-design.md)."""
        return None if self._has_plan() else super().search_region()

    def _fix_bias_on(self) -> bool:
        return self.dim >= 6 and self._has_plan()

    @property
    def models_walk_offset(self) -> bool:
        return self._fix_bias_on()

    def predict(self, step: Step) -> None:
        """The step (``_step``); its joint moments kept as ``step_joint`` for the smoother: each
        particle's state paired with its ancestor's, followed through kills, resamplings and redraws
        by the descent record the particle smoother reads (kept as it was for a replay)."""
        before, kept = self.particles[:, : selfcal.N_AUG].copy(), self.lineage
        self.lineage = np.arange(len(before))
        self._step(step)
        rows, self.lineage = self.lineage, None if kept is None else kept[self.lineage]
        pairs = np.hstack((before[rows], self.particles[:, : selfcal.N_AUG]))
        self.step_joint = (StepJoint.of(self.weights @ pairs[:, : selfcal.N_AUG], weighted_covariance(pairs, self.weights))
                           if np.isfinite(pairs).all() else None)  # (else the model's gain)

    def _step(self, step: Step) -> None:
        n = len(self.particles)
        rng = self.rng
        P = self.particles
        P[:, 2] += math.radians(self._cal["bias_walk_deg"]) * rng.standard_normal(n)
        P[:, 3] = np.clip(P[:, 3] + self._cal["scale_walk"] * rng.standard_normal(n), *selfcal.SCALE_RANGE)
        if self._fix_bias_on():
            phi = math.exp(-1.0 / self.params["fix_bias_steps"])
            P[:, 4:6] = phi * P[:, 4:6] + math.sqrt(1.0 - phi * phi) * rng.standard_normal((n, 2))
            if self.dim == 7:
                flip = rng.random(n) < self.params["fix_bias_switch"]
                P[flip, 6] = 1.0 - P[flip, 6]
        d = P[:, 3] * (step.length_m + step.length_std_m * rng.standard_normal(n))
        h = math.radians(step.heading_deg) + P[:, 2] + math.radians(step.heading_std_deg) * rng.standard_normal(n)
        moved = P.copy(order="F")
        moved[:, 0] += d * np.sin(h)
        moved[:, 1] += d * np.cos(h)
        moved[:, :2] += math.sqrt(self.params["q"]) * rng.standard_normal((n, 2))
        self._settle(moved, step.length_m)
        self._observe_grid(step)

    def _observe_grid(self, step: Step) -> None:
        """The building's grid per straight run (``selfcal.Calibrating._observe_grid``) as a
        likelihood, when the cloud's mean offset from it (mod 90°: the weighted circular mean of
        4rᵢ, /4) is within ``grid_gate_deg``: each particle is weighed by π·N(rᵢ; 0, σ) + (1 − π)/90°,
        rᵢ the offset of the run's heading + bᵢ from the nearest grid direction, σ
        ``grid_sigma_deg`` and π ``grid_on_share`` (a share of runs cross open space at any angle:
        a particle that puts this run off the grid is less likely, not ruled out). Without a plan the
        cloud is then kept as wide as a Kalman update of its moments by the observation would leave
        it (``kalman_floor``); with a plan, which has no such floor, σ² also counts the run's own
        heading noise (the step's declared σ² over the run's n steps), so the weighing takes no more
        spread than the run can tell. Mod 90° all through, so a cloud that holds two biases 90° apart
        keeps both. On a floor with a plan only with ``grid_plan`` 1 (the default)."""
        p, plan = self.params, self._has_plan()
        if plan and not p["grid_plan"]:
            return
        offset = self._grid_offset(step)
        if offset is None:
            return
        r = np.radians(selfcal.wrap_deg(offset - np.degrees(self.particles[:, 2]), 90.0))
        mean_r = math.degrees(np.angle(self.weights @ np.exp(4j * r))) / 4.0
        if abs(mean_r) > p["grid_gate_deg"]:
            return
        sigma, share = math.radians(p["grid_sigma_deg"]), p["grid_on_share"]
        if plan:  # (no Kalman floor there: the run's own heading noise keeps the bias spread)
            sigma = math.sqrt(sigma**2 + math.radians(step.heading_std_deg) ** 2 / max(self._run.n, 1))
        loglik = -0.5 * (r / sigma) ** 2
        if share < 1.0:
            loglik = np.log(share * np.exp(loglik) / (math.sqrt(2.0 * math.pi) * sigma) + (1.0 - share) / (0.5 * math.pi))
        floor = self._kalman_floor(np.array([[0.0, 0.0, 1.0, 0.0]]), np.array([[sigma**2]]),
                                   np.array([math.radians(mean_r)]))
        if self._reweight(loglik) and floor is not None:
            self._keep_spread(*floor)

    def _observe_bias(self, innovation: float, var: float, x: selfcal.Vec4 | None = None,
                      P: selfcal.Mat4 | None = None) -> None:
        """An observation of b (``Calibrating.observe_heading``) as the cloud's form of a Kalman
        update: every particle's b moved and drawn in as the update moves the b column's weighted
        mean m and variance v (bᵢ ← m + K·innovation + √(1 − K)·(bᵢ − m), K = v / (v + ``var``)),
        the other columns as they are. A reweighing would leave almost no particle where a phone
        45° off its compass says its bias is."""
        b = self.particles[:, 2]
        m = float(self.weights @ b)
        v = float(self.weights @ (b - m) ** 2)
        k = v / (v + var) if v + var > 0 else 0.0
        self.particles[:, 2] = m + k * innovation + math.sqrt(1.0 - k) * (b - m)
        moved = np.zeros(self.particles.shape[1], bool)
        moved[2] = True
        self.particles = self._round(self.particles, refit=moved)

    def update(self, fix: Fix) -> None:
        floor = self._kalman_floor(np.eye(2, 4), fix_cov(fix.covariance), np.asarray(fix.mean, float) - self.mean)
        if self._reweight(self._fix_loglik(fix)) and floor is not None:
            self._keep_spread(*floor)

    def update_range(self, beacon_xy, range_m: float, range_std_m: float, on_wall=None) -> bool:
        if not range_usable(range_m, range_std_m, self.params["max_range_m"]):
            return False
        m, beacon = self.state_mean, np.asarray(beacon_xy, float).reshape(2)
        z, sigma = log_range(range_m, range_std_m)
        floor = self._kalman_floor(log_range_H(m, beacon), np.array([[sigma**2]]), z - log_range_h(m, beacon))
        used = self._reweight(self._range_loglik(beacon_xy, range_m, range_std_m, on_wall))
        if used and floor is not None:
            self._keep_spread(*floor)
        return used

    def _kalman_floor(self, H: np.ndarray, R: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Before a measurement (Jacobian ``H`` on [x, y, b, s], noise ``R``, innovation ``y``):
        the covariance a Kalman update of the cloud's own moments would leave, and γ = min(1,
        d²/χ²'s 99 % point), d² = yᵀ S⁻¹ y; None when ``kalman_floor`` is off or the floor has a plan."""
        if self.params["kalman_floor"] <= 0 or self._has_plan():
            return None
        P = self.state_covariance
        PH = P @ H.T
        S_inv = np.linalg.inv(H @ PH + R)
        d2 = float(y @ S_inv @ y)
        return P - PH @ S_inv @ PH.T, min(1.0, d2 / CHI2_99[len(y)])

    def _keep_spread(self, floor: np.ndarray, gamma: float) -> None:
        """Add N(0, D) to [x, y, b, s]: D = κ·(the positive part of ``floor`` − the cloud's
        covariance), its b and s rows and columns scaled by √γ.

        Why: a measurement reweights the particles but moves none, so after a few the cloud is
        narrower than the information in them allows (the weight piles onto the few particles
        nearest the measurement; a strong beacon range can leave one), most of all in the
        calibration columns; a later drift of the heading then finds no particle to follow it,
        and the estimate is confident and wrong (NEES ≫ 4 on the stress scenarios of
        benchmarks/scenario_family.py). A Kalman update of the cloud's own mean and covariance
        is the spread the measurement allows. The calibration's share follows the
        measurement's disagreement γ: one that agrees is no sign that the heading or the scale
        is off, so it adds their spread only as far as it disagrees. Without a plan only:
        where walls kill particles the cloud's shape is the plan's, not a Gaussian's."""
        shortfall = floor - self.state_covariance
        w, V = np.linalg.eigh(0.5 * (shortfall + shortfall.T))
        if w[-1] <= 0:
            return
        root = V * np.sqrt(self.params["kalman_floor"] * np.maximum(w, 0.0))
        root[2:] *= math.sqrt(gamma)
        P = self.particles
        P[:, :4] += self.rng.standard_normal((len(P), 4)) @ root.T
        P[:, 3] = np.clip(P[:, 3], *selfcal.SCALE_RANGE)
        moved = np.zeros(P.shape[1], bool)
        moved[:4] = np.any(root != 0.0, axis=1)  # (a column whose row of the root is 0 did not move)
        self.particles = self._round(P, refit=moved)  # (the weights are as stored: ``_reweight``)

    def _fix_loglik(self, fix: Fix) -> np.ndarray:
        """N(z; p_i + √ρ·L·u_i, (1 − ρ)·R) with the fixes' shared error (a fix that shares it),
        else the seed form's."""
        if fix.shared_share == 0.0 or not self._fix_bias_on():
            return super()._fix_loglik(fix)
        R = fix_cov(fix.covariance)
        if self.dim == 6:
            rho = self.params["fix_bias_share"]
            bias = math.sqrt(rho) * self.particles[:, 4:6] @ np.linalg.cholesky(R).T
            return gaussian_loglik(self.particles[:, :2] + bias, fix.mean, (1.0 - rho) * R)
        rho = self.params["fix_bias_share"] * self.particles[:, 6]  # (a hypothesis per particle)
        bias = np.sqrt(rho)[:, None] * (self.particles[:, 4:6] @ np.linalg.cholesky(R).T)
        return gaussian_loglik(self.particles[:, :2] + bias, fix.mean, R) / (1.0 - rho) - np.log(1.0 - rho)

    @property
    def fix_bias_learned(self) -> float | None:
        """The share of a fix's variance the cloud takes as the walk's shared error (the weighted
        mean of ρkᵢ); None unless it is learned (``fix_bias_switch`` > 0)."""
        if self.dim != 7:
            return None
        return float(self.params["fix_bias_share"] * (self.weights @ self.particles[:, 6]))

    def reset(self, mean, cov) -> None:
        n = self.params["n_particles"]
        L = np.linalg.cholesky(as_cov(cov))
        xy = as_mean(mean) + self.rng.standard_normal((n, 2)) @ L.T
        old = getattr(self, "particles", None)
        if old is None or old.shape[1:] != (self.dim,):
            cal = np.column_stack((math.radians(self._cal["bias0_std_deg"]) * self.rng.standard_normal(n),
                                   np.clip(1.0 + self._cal["scale0_std"] * self.rng.standard_normal(n),
                                           *selfcal.SCALE_RANGE)))
            if self.dim >= 6:
                cal = np.column_stack((cal, self.rng.standard_normal((n, 2))))
            if self.dim == 7:
                cal = np.column_stack((cal, (np.arange(n) % 2).astype(float)))
        else:  # keep the calibration the particles learned (their weights carry over to it)
            cal = old[systematic_resample(self.weights, float(self.rng.random()), n), 2:]
        self.particles = np.column_stack((xy, cal))
        self.weights = np.full(n, 1.0 / n)
        self._descend(None)
        self._quantize()

    def inflate(self, factor: float) -> None:
        """Spread position and calibration about their mean by √factor (u keeps its unit prior)."""
        m = self.weights @ self.particles[:, :4]
        self.particles[:, :4] = m + math.sqrt(float(factor)) * (self.particles[:, :4] - m)
        self.particles[:, 3] = np.clip(self.particles[:, 3], *selfcal.SCALE_RANGE)
        self._quantize()

    def _state(self) -> dict:
        return {**super()._state(), "dim": self.dim, **self._run_state()}

    def _load_state(self, state: dict) -> None:
        stored = state.get("dim", 4)
        if stored != self.dim:  # stored before the shared error (4) or before it was learned (6): go on as it started
            self._set_fix_bias(self.params["fix_bias_share"] if stored == 6 else 0.0, self.params["fix_bias_steps"], 0.0)
        super()._load_state(state)
        self._load_run(state)

    @property
    def state_mean(self) -> np.ndarray:
        """[x, y, b, s]."""
        return self.weights @ self.particles[:, :4]

    @property
    def state_covariance(self) -> np.ndarray:
        return weighted_covariance(self.particles[:, :4], self.weights)
