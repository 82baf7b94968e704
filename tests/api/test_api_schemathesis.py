"""A short schemathesis pass over the OpenAPI document, in-process (ASGI), with the write token.

Every check runs except ``positive_data_acceptance``: two inter-parameter rules OpenAPI cannot state
(``points`` only with ``format=points``; ``until`` after ``since``) answer a documented 422 for inputs each
valid on its own. The full ≥ 5-min CLI runs (docs/design/api.md, "Fuzzing") include that check too.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import positive_data_acceptance
from schemathesis.config import SchemathesisConfig

from api.app import create_app
from service.settings import Settings
from simulator.served import DEMO_FED, served_service
from tests.api.conftest import WRITE_TOKEN, served_map_mode, sqlite_url

pytestmark = pytest.mark.slow  # property-based runs over every operation (~20 s each at load 8)


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory: pytest.TempPathFactory) -> Iterator[schemathesis.BaseSchema]:
    """The real service with the demo plan's first 22 min (its clock does not move: the data stay fresh);
    the fuzzer's POSTs start real identifications on it."""
    url = sqlite_url(tmp_path_factory.mktemp("schemathesis"))
    with served_service(database_url=url, feed_samples=DEMO_FED) as s:
        app = create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)
        # the CLI runs' configuration: 413 and 414 (the API's body and URL caps) count as rejecting bad input
        config = SchemathesisConfig.from_path(str(Path(__file__).with_name("schemathesis.toml")))
        yield schemathesis.openapi.from_asgi("/api/v1/openapi.json", app, config=config)


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=15, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_api_conforms_to_its_openapi(case: schemathesis.Case) -> None:
    case.call_and_validate(
        headers={"Authorization": f"Bearer {WRITE_TOKEN}"}, excluded_checks=[positive_data_acceptance]
    )


@pytest.fixture(scope="module")
def map_schema(tmp_path_factory: pytest.TempPathFactory) -> Iterator[schemathesis.BaseSchema]:
    """The real service in speed-map mode after several map fits (tests/api/conftest.py, MAP_PLAN): every
    operation again, as answers depend on the mode (/chtc from the map, /chtc/map's 200, the map fits in
    /identifications, /compensation with the map's H), against the same document."""
    with served_map_mode(tmp_path_factory.mktemp("schemathesis-map")) as s:
        app = create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)
        config = SchemathesisConfig.from_path(str(Path(__file__).with_name("schemathesis.toml")))
        yield schemathesis.openapi.from_asgi("/api/v1/openapi.json", app, config=config)


map_mode = schemathesis.pytest.from_fixture("map_schema")


@map_mode.parametrize()
@settings(max_examples=5, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_speed_map_mode_conforms_to_the_openapi(case: schemathesis.Case) -> None:
    case.call_and_validate(
        headers={"Authorization": f"Bearer {WRITE_TOKEN}"}, excluded_checks=[positive_data_acceptance]
    )
