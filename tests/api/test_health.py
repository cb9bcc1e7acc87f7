"""/healthz: 200 while the database answers, 503 naming the driver's error when it does not."""

from __future__ import annotations

from server.api.deps import health_service
from server.db import Database
from server.services.health import HealthService


def test_healthz_is_503_when_the_database_does_not_answer(live_server, anonymous, tmp_path):
    assert anonymous.get("/healthz").json() == {"status": "ok"}
    unreachable = Database(f"sqlite:///{tmp_path}/missing-dir/db.sqlite")
    live_server.app.dependency_overrides[health_service] = lambda: HealthService(unreachable)
    try:
        answer = anonymous.get("/healthz")
    finally:
        live_server.app.dependency_overrides.clear()
        unreachable.dispose()
    assert answer.status_code == 503 and answer.json() == {"detail": "database unavailable: OperationalError"}
    assert anonymous.get("/healthz").status_code == 200
