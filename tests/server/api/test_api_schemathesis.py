"""Schemathesis over the whole OpenAPI description, against the app with its lifespan
(a real SQLite file): no 5xx, every status documented, every body and content type as
described (issue 15, "keep it closed"). A few examples per operation here; ``make
bench`` runs the slow variant with 200 per operation.

Requests carry the admin key (authorization has its own matrix test). The fuzzer may
revoke any key, its own too: the last active admin key is refused with 409, so no
operation can lock the later ones out.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import schemathesis
from api_helpers import ADMIN_KEY, camera_of, make_settings
from hypothesis import HealthCheck, Phase, given, settings
from schemathesis import checks
from schemathesis.specs.openapi import checks as openapi_checks

CHECKS = [
    checks.not_a_server_error,
    openapi_checks.status_code_conformance,
    openapi_checks.content_type_conformance,
    openapi_checks.response_schema_conformance,
]
HEADERS = {"X-API-Key": ADMIN_KEY}


def _operation_labels() -> list[str]:
    from monoloc.server.api.app import create_app
    from monoloc.server.settings import Settings

    spec = create_app(Settings(data_dir="unused")).openapi()  # no lifespan: nothing written
    return [f"{m.upper()} {p}" for p, ops in spec["paths"].items() for m in ops]


OPERATIONS = _operation_labels()


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory) -> Iterator:
    from monoloc.server.api.app import create_app

    app = create_app(make_settings(tmp_path_factory.mktemp("schemathesis") / "data"))
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    case = schema["/v1/maps"]["POST"].Case(body={"name": "fuzz", "camera": camera_of(None)})
    assert case.call(headers=HEADERS).status_code == 201  # map 1 exists: ids hit something
    revoke = schema["/v1/keys/{key_id}"]["DELETE"].Case(path_parameters={"key_id": 1})
    assert revoke.call(headers=HEADERS).status_code == 409  # the fuzzer cannot lock itself out
    yield schema


def _fuzz(api_schema, label: str, max_examples: int) -> None:
    method, path = label.split(" ", 1)
    operation = api_schema[path][method]

    @given(case=operation.as_strategy())
    @settings(
        max_examples=max_examples,
        deadline=None,
        database=None,
        derandomize=True,
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    def run(case) -> None:
        response = case.call(headers=HEADERS)
        case.validate_response(response, checks=CHECKS)

    run()


@pytest.mark.parametrize("label", OPERATIONS)
def test_operation_conforms(api_schema, label):
    _fuzz(api_schema, label, max_examples=4)


@pytest.mark.slow
@pytest.mark.parametrize("label", OPERATIONS)
def test_operation_conforms_thoroughly(api_schema, label):
    _fuzz(api_schema, label, max_examples=200)
