"""Schemathesis over every operation of the published OpenAPI document, with an admin and a
device key: no answer is a 5xx, and every answer matches the schema the document publishes.

Marked ``fuzz``: the default suite skips it; ``.ci/run`` runs it (``pytest -m fuzz``) on SQLite.
Valid and invalid requests (schemathesis' positive and negative generation); bounded: a fixed
number of derandomized examples per operation and key (about two minutes).
"""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import response_schema_conformance

from server.app import create_app
from tests.conftest import ADMIN_KEY, DEVICE_KEY, make_settings

pytestmark = pytest.mark.fuzz

#: operations that stream (server-sent events) or serve the dashboard's pages are not JSON API calls
SKIPPED_PATHS = r"(/events$|^/$|^/dashboard|^/docs|^/static)"
EXAMPLES = 40


@pytest.mark.parametrize("key", [ADMIN_KEY, DEVICE_KEY], ids=["admin", "device"])
def test_no_operation_answers_5xx_or_off_schema(clean_db, key):
    app = create_app(make_settings(clean_db, embedded_worker=False, auth_failures_per_minute=10**6))
    schema = schemathesis.openapi.from_asgi("/openapi.json", app).exclude(path_regex=SKIPPED_PATHS)
    failures: list[str] = []
    statuses: dict[int, int] = {}
    operations = 0
    for result in schema.get_all_operations():
        operation = result.ok()
        operations += 1

        @given(case=st.one_of(operation.as_strategy(), operation.as_strategy(GenerationMode.NEGATIVE)))
        @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        def run(case) -> None:
            answer = case.call_and_validate(headers={"Authorization": f"Bearer {key}"},
                                            checks=[not_a_server_error, response_schema_conformance])
            statuses[answer.status_code] = statuses.get(answer.status_code, 0) + 1

        try:
            run()
        except Exception as exc:  # one report per failing operation, every operation tried
            failures.append(f"{operation.method.upper()} {operation.path}: {str(exc)[:3000]}")
    print(f"{operations} operations, answers by status: {dict(sorted(statuses.items()))}")
    assert operations >= 20 and sum(statuses.values()) >= operations * 10
    assert not failures, "\n\n".join(failures)
