"""PROTOTYPE: a bank of two phone models, weighed by how well each predicts the fixes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from server.estimation.tracking import selfcal
from server.estimation.tracking.base import FixInnovation, Tracker, make_tracker, register, symmetric, tracker_from_dict
from server.estimation.types import Fix, Step


def _moments(weights: np.ndarray, means: list[np.ndarray], covs: list[np.ndarray], angle: int | None = None):
    ref = means[0]
    diffs = []
    for m in means:
        d = m - ref
        if angle is not None:
            d[angle] = selfcal.wrap_deg(math.degrees(d[angle])) * math.pi / 180.0
        diffs.append(d)
    mean_d = sum(w * d for w, d in zip(weights, diffs, strict=True))
    cov = sum(w * (P + np.outer(d - mean_d, d - mean_d)) for w, d, P in zip(weights, diffs, covs, strict=True))
    return ref + mean_d, symmetric(cov)


@register
class EKFBankTracker(selfcal.Calibrating, Tracker):
    name = "ekf-bank"
    supports_range = True
    base = "ekf"

    def __init__(self, initial_mean, initial_cov, walls=None, seed=None, bank_tempering: float = 1.0,
                 bank_switch: float = 0.02, calibrated_bias0_deg: float = 2.0, bank_scorer: float = 1.0, **params):
        super().__init__(initial_mean, initial_cov, walls=walls, seed=seed)
        self.components = [
            make_tracker(self.base, initial_mean, initial_cov, walls=walls, seed=seed, **params),
            make_tracker(self.base, initial_mean, initial_cov, walls=walls, seed=seed,
                         **{**params, "bias0_std_deg": calibrated_bias0_deg, "walk_offset": 2}),
        ]
        self.scorers = [
            make_tracker(self.base, initial_mean, initial_cov, walls=walls, seed=seed, **{**params, "walk_offset": 1}),
            make_tracker(self.base, initial_mean, initial_cov, walls=walls, seed=seed,
                         **{**params, "bias0_std_deg": calibrated_bias0_deg, "walk_offset": 1}),
        ] if bank_scorer else self.components
        self.params = {**self.components[0].params, "bank_tempering": float(bank_tempering), "bank_scorer": float(bank_scorer),
                       "bank_switch": float(bank_switch), "calibrated_bias0_deg": float(calibrated_bias0_deg)}
        self.logw = np.log(np.full(len(self.components), 1.0 / len(self.components)))

    @property
    def weights(self) -> np.ndarray:
        w = np.exp(self.logw - self.logw.max())
        return w / w.sum()

    def predict(self, step: Step) -> None:
        for c in self._all():
            c.predict(step)

    def update(self, fix: Fix) -> None:
        R = np.asarray(fix.covariance, float)
        w = self.weights
        pi = self.params["bank_switch"]
        w = (1 - pi) * w + pi / len(w)
        ll = []
        for c in self.scorers:
            inn = c.fix_innovation(fix)
            S = inn.covariance + inn.noise_share * R
            y = inn.innovation
            ll.append(-0.5 * (float(y @ np.linalg.solve(S, y)) + math.log(np.linalg.det(S))))
        self.logw = np.log(w) + self.params["bank_tempering"] * np.array(ll)
        self.logw -= self.logw.max()
        for c in self._all():
            c.update(fix)

    def _all(self):
        return self.components if self.scorers is self.components else self.components + self.scorers

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
        used = [c.update_range(beacon_xy, range_m, range_std_m, on_wall) for c in self._all()]
        return any(used)

    @property
    def state_mean(self) -> np.ndarray:
        return _moments(self.weights, [c.state_mean[:4] for c in self.components],
                        [c.state_covariance[:4, :4] for c in self.components], angle=2)[0]

    @property
    def state_covariance(self) -> np.ndarray:
        return _moments(self.weights, [c.state_mean[:4] for c in self.components],
                        [c.state_covariance[:4, :4] for c in self.components], angle=2)[1]

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

    def _state(self) -> dict[str, Any]:
        return {"mean": self.mean.tolist(), "cov": self.covariance.tolist(), "logw": self.logw.tolist(),
                "components": [c.to_dict(walls=False) for c in self.components],
                "scorers": None if self.scorers is self.components else [c.to_dict(walls=False) for c in self.scorers]}

    def _load_state(self, state: dict[str, Any]) -> None:
        self.logw = np.asarray(state["logw"], float)
        self.components = [tracker_from_dict(d) for d in state["components"]]
        self.scorers = self.components if state["scorers"] is None else [tracker_from_dict(d) for d in state["scorers"]]
        for c in self._all():
            c.set_walls(self.walls)
