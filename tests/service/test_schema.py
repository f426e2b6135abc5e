"""Property-based run of the OpenAPI schema (schemathesis) against the real app over HTTP:
no 5xx, and every response conforms to its documented schema."""

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import response_schema_conformance  # noqa: E402

from .test_api import TOKEN, service  # noqa: E402,F401  (the real server fixture)


def test_every_operation(service):  # noqa: F811
    from ardflow.service.client import Client

    url, _ = service
    schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
    ops = [r.ok() for r in schema.get_all_operations()]
    assert len(ops) >= 11
    seen = []
    try:
        for op in ops:
            @given(case=op.as_strategy())
            @settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), database=None)
            def run(case):
                resp = case.call_and_validate(headers={"X-API-Token": TOKEN},
                                              checks=[not_a_server_error, response_schema_conformance])
                seen.append(resp.status_code)

            run()
    finally:
        # any study a fuzzed request managed to start is cancelled, so nothing keeps running
        with Client(url, token=TOKEN) as c:
            for s in c.studies():
                if s["status"] in ("queued", "running"):
                    c.cancel(s["id"])
    assert seen and max(seen) < 500
