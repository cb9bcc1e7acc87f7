"""Model gating (``"activate": "if_better"``): a model trained so becomes active only when its
held-out mean error is no worse than the active model's; the decision is in its metrics."""

from __future__ import annotations

from datetime import UTC, datetime

from server.domain import ModelInfo
from server.services.training import decide_activation
from tests.api.test_models import site, train  # noqa: F401  (the site fixture)

#: averaging 30 neighbours over a 12-point floor: a deliberately worse model than k=3
WORSE = {"algorithm": "knn", "params": {"k": 30, "weights": "uniform", "floor_k": 30}}
BETTER = {"algorithm": "knn", "params": {"k": 3}}


def _active(admin, site_id: int) -> list[int]:
    return [m["id"] for m in admin.get(f"/api/v1/sites/{site_id}/models").json() if m["active"]]


def test_if_better_activates_a_better_model_only_and_records_why(admin, site):  # noqa: F811
    first = train(admin, site, activate="if_better", **WORSE)
    assert first["status"] == "ready" and first["active"] is True and first["activate"] == "if_better"
    decision = first["metrics"]["activation"]
    assert decision["activated"] is True and decision["active_model_id"] is None  # nothing was active

    better = train(admin, site, activate="if_better", **BETTER)
    assert better["metrics"]["mean_error_m"] <= first["metrics"]["mean_error_m"]
    decision = better["metrics"]["activation"]
    assert decision == {**decision, "requested": "if_better", "activated": True, "active_model_id": first["id"],
                        "mean_error_m": better["metrics"]["mean_error_m"],
                        "active_mean_error_m": first["metrics"]["mean_error_m"]}
    assert better["active"] is True and _active(admin, site["id"]) == [better["id"]]

    worse = train(admin, site, activate="if_better", **WORSE)
    assert worse["metrics"]["mean_error_m"] > better["metrics"]["mean_error_m"]
    decision = worse["metrics"]["activation"]
    assert decision["activated"] is False and decision["active_model_id"] == better["id"]
    assert worse["active"] is False and _active(admin, site["id"]) == [better["id"]]  # the active one stays

    # the default keeps today's behaviour: the site has an active model, so a new one waits
    plain = train(admin, site, **BETTER)
    assert plain["activate"] == "if_none" and plain["active"] is False
    assert plain["metrics"]["activation"]["activated"] is False


def test_activate_must_be_a_known_mode(admin, site):  # noqa: F811
    answer = admin.post(f"/api/v1/sites/{site['id']}/models", json={"algorithm": "knn", "activate": "maybe"})
    assert answer.status_code == 422 and "activate" in answer.text


def test_algorithm_defaults_to_wknn(admin, site):  # noqa: F811
    model = train(admin, site)
    assert model["algorithm"] == "wknn" and model["status"] == "ready", model


def _model(model_id: int, error: float | None, pooled: bool | None = None) -> ModelInfo:
    now = datetime.now(UTC)
    metrics = None if error is None else {"mean_error_m": error}
    if metrics is not None and pooled is not None:
        metrics["held_out_pooled"] = pooled
    return ModelInfo(model_id, 1, "knn", {}, False, (), True, "ready", None, True, 100, metrics, now, now)


def test_decisions_without_a_figure_to_compare():
    assert decide_activation("if_better", None, None).activated  # nothing active: any model serves
    assert not decide_activation("if_better", None, _model(1, 3.0)).activated  # unmeasured never displaces
    assert decide_activation("if_better", 5.0, _model(1, None)).activated  # the active one was never measured
    assert decide_activation("if_better", 3.0, _model(1, 3.0)).activated  # no worse is enough
    assert not decide_activation("never", 1.0, None).activated
    assert decide_activation("always", 9.0, _model(1, 1.0)).activated


def test_a_pooled_figure_is_not_compared_with_one_split():
    # a model trained before the pooled figures (no key) or on one split holds a figure of another kind
    for old in (_model(1, 9.0), _model(1, 9.0, pooled=False)):
        decision = decide_activation("if_better", 2.0, old, pooled=True)
        assert not decision.activated and "not comparable" in decision.reason and "'always'" in decision.reason
    assert not decide_activation("if_better", 2.0, _model(1, 9.0, pooled=True), pooled=False).activated
    assert decide_activation("if_better", 2.0, _model(1, 9.0, pooled=True), pooled=True).activated
    assert not decide_activation("if_better", 9.5, _model(1, 9.0, pooled=True), pooled=True).activated
    assert decide_activation("if_better", 2.0, _model(1, 9.0), pooled=False).activated  # both from one split
