"""PROTOTYPE: a Gaussian sum over the walk's initial heading bias (a compass that aligned the PDR
heading may be far off), each component a self-calibrating filter, weighed by its fixes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from server.estimation.tracking import selfcal
from server.estimation.tracking.base import FixInnovation, Tracker, make_tracker, register, symmetric, tracker_from_dict
from server.estimation.types import Fix, Step


def _moments(weights, means, covs):
    ref = means[0]
    diffs = []
    for m in means:
        d = m - ref
        d[2] = math.remainder(float(d[2]), 2 * math.pi)
        diffs.append(d)
    mean_d = sum(w * d for w, d in zip(weights, diffs, strict=True))
    cov = sum(w * (P + np.outer(d - mean_d, d - mean_d)) for w, d, P in zip(weights, diffs, covs, strict=True))
    return ref + mean_d, symmetric(cov)


class CompassBank(selfcal.Calibrating, Tracker):
    base = "ekf"
    supports_range = True

    def __init__(self, initial_mean, initial_cov, walls=None, seed=None, compass_off_deg: float = 45.0,
                 compass_share: float = 0.1, compass_prune: float = 1e-4, compass_grid_share: float = 0.6, compass_scorer: float = 1.0, **params):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        offs = [0.0] if compass_share <= 0 else [0.0, compass_off_deg, -compass_off_deg]
        def turned(o, **extra):
            c = make_tracker(self.base, initial_mean, initial_cov, walls=walls, seed=seed, **{**params, **extra})
            x, P = c.state_mean, c.state_covariance
            x[2] = math.radians(o)
            c._set_state(x, P)
            return c

        self.components = [turned(o) for o in offs]
        # each hypothesis scored under the walk's fix offset (the fixes' shared error integrated out)
        self.scorers = [turned(o, walk_offset=1) for o in offs] if compass_scorer else self.components
        prior = np.array([1.0 - compass_share] + [compass_share / 2] * (len(offs) - 1))
        self.logw = np.log(prior)
        self.params = {**self.components[0].params, "compass_off_deg": float(compass_off_deg),
                       "compass_share": float(compass_share), "compass_prune": float(compass_prune),
                       "compass_grid_share": float(compass_grid_share), "compass_scorer": float(compass_scorer)}

    @property
    def weights(self) -> np.ndarray:
        w = np.exp(self.logw - self.logw.max())
        return w / w.sum()

    def predict(self, step: Step) -> None:
        share = self.params["compass_grid_share"]
        offset = self._grid_offset(step) if share > 0 and len(self.components) > 1 else None
        if offset is not None:
            var = math.radians(self.params["grid_sigma_deg"]) ** 2
            ll = []
            for c in self.scorers:
                b, pbb = float(c.state_mean[2]), float(c.state_covariance[2, 2])
                r = math.radians(selfcal.wrap_deg(offset - math.degrees(b), 90.0))
                S = pbb + var
                on = share * math.exp(-0.5 * r * r / S) / math.sqrt(2 * math.pi * S)
                ll.append(math.log(on + (1 - share) / (0.5 * math.pi)))
            self.logw = self.logw + np.array(ll)
            self.logw -= self.logw.max()
        for c in self._all():
            c.predict(step)
        if offset is not None:
            self._prune()

    def update(self, fix: Fix) -> None:
        R = np.asarray(fix.covariance, float)
        ll = []
        for c in self.scorers:
            inn = c.fix_innovation(fix)
            S = inn.covariance + inn.noise_share * R
            y = inn.innovation
            ll.append(-0.5 * (float(y @ np.linalg.solve(S, y)) + math.log(np.linalg.det(S))))
        self.logw = self.logw + np.array(ll)
        self.logw -= self.logw.max()
        for c in self._all():
            c.update(fix)
        self._prune()

    def _all(self):
        return self.components if self.scorers is self.components else self.components + self.scorers

    def _prune(self) -> None:
        w = self.weights
        keep = w >= self.params["compass_prune"]
        if keep.all():
            return
        same = self.scorers is self.components
        self.components = [c for c, k in zip(self.components, keep, strict=True) if k]
        self.scorers = self.components if same else [c for c, k in zip(self.scorers, keep, strict=True) if k]
        self.logw = self.logw[keep]

    def fix_innovation(self, fix: Fix) -> FixInnovation:
        R = np.asarray(fix.covariance, float)
        w = self.weights
        inns = [c.fix_innovation(fix) for c in self.components]
        z = np.asarray(fix.mean, float)
        mus = [z - i.innovation for i in inns]
        mu = sum(wk * m for wk, m in zip(w, mus, strict=True))
        ns = float(sum(wk * i.noise_share for wk, i in zip(w, inns, strict=True)))
        cov = sum(wk * (i.covariance + (i.noise_share - ns) * R + np.outer(m - mu, m - mu))
                  for wk, i, m in zip(w, inns, mus, strict=True))
        return FixInnovation(z - mu, symmetric(cov), ns)

    def update_range(self, beacon_xy, range_m: float, range_std_m: float, on_wall=None) -> bool:
        return any([c.update_range(beacon_xy, range_m, range_std_m, on_wall) for c in self._all()])

    @property
    def state_mean(self) -> np.ndarray:
        return _moments(self.weights, [c.state_mean[:4] for c in self.components],
                        [c.state_covariance[:4, :4] for c in self.components])[0]

    @property
    def state_covariance(self) -> np.ndarray:
        return _moments(self.weights, [c.state_mean[:4] for c in self.components],
                        [c.state_covariance[:4, :4] for c in self.components])[1]

    @property
    def mean(self) -> np.ndarray:
        return self.state_mean[:2]

    @property
    def covariance(self) -> np.ndarray:
        return self.state_covariance[:2, :2]

    def reset(self, mean, cov) -> None:
        for c in self._all():
            c.reset(mean, cov)

    def inflate(self, factor: float) -> None:
        for c in self._all():
            c.inflate(factor)

    def set_walls(self, walls) -> None:
        super().set_walls(walls)
        for c in self._all():
            c.set_walls(walls)

    def set_walkable(self, walkable) -> None:
        super().set_walkable(walkable)
        for c in self._all():
            c.set_walkable(walkable)

    def set_survey_grid(self, grid) -> None:
        super().set_survey_grid(grid)
        for c in self._all():
            c.set_survey_grid(grid)

    def _state(self) -> dict[str, Any]:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist(), "logw": self.logw.tolist(),
                "components": [c.to_dict(walls=False) for c in self.components],
                "scorers": None if self.scorers is self.components else [c.to_dict(walls=False) for c in self.scorers],
                **self._run_state()}

    def _load_state(self, state: dict[str, Any]) -> None:
        self.logw = np.asarray(state["logw"], float)
        self._load_run(state)
        self.components = [tracker_from_dict(d) for d in state["components"]]
        self.scorers = self.components if state.get("scorers") is None else [tracker_from_dict(d) for d in state["scorers"]]
        for c in self._all():
            c.set_walls(self.walls)


@register
class EKFCompass(CompassBank):
    name = "ekf-compass"
    base = "ekf"
