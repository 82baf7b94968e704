"""The compensation zero through the API on the real service (``simulator.served``, real SQLite):
``POST /compensation/reference`` needs the write token, refuses a zero the live field cannot give and says
why, stores what it is given, and a stored zero survives restarts, also a warm one, where a service without it
would re-zero on the warm spindle."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from api.app import create_app
from model.plant import Segment
from service.commands.commission import zero
from service.settings import Settings
from service.store.models import CompensationReferenceRow
from simulator.served import Plan, feed, served_service
from tests.modes import per_condition

from .conftest import DEMO_WINDOWS, WRITE_TOKEN, LiveServer, sqlite_url

AUTH = {"Authorization": f"Bearer {WRITE_TOKEN}"}
REF = "/api/v1/compensation/reference"
# 20 min at rest at 22 °C from equilibrium (a cold spindle before any machining), then 4000 rpm for 25 min
COLD_THEN_WARM = Plan(profile=(Segment(1200.0, 0.0, 0.0, 22.0), Segment(1500.0, 4000.0, 14.0, 22.0)))
REST_SAMPLES = 120


def test_zero_needs_the_token_refuses_while_turning_and_stores_a_given_temperature(
    client: TestClient,
) -> None:
    assert client.get(REF).status_code == 404
    assert client.post(REF).status_code == 401
    r = client.post(REF, headers=AUTH)  # the demo plan's spindle turns at 4000 rpm
    assert r.status_code == 409 and "turns" in r.json()["error"]["message"], r.text
    assert client.post(REF, headers=AUTH, json={"temperature_c": 1e6}).status_code == 422
    r = client.post(REF, headers=AUTH, json={"temperature_c": 21.5, "set_by": "alice"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["temperature_c"] == 21.5 and body["sd_c"] == 0.0
    assert body["source"] == "api" and body["set_by"] == "alice"
    assert client.get(REF).json() == body
    comp = client.get("/api/v1/compensation").json()
    assert comp["t_ref_c"] == 21.5 and comp["reference"] == body
    assert comp["reason_code"] != "no_reference"


@pytest.mark.slow
def test_a_zero_taken_cold_survives_a_warm_restart(tmp_path: Path) -> None:
    settings = per_condition(
        Settings(api={"token": WRITE_TOKEN}, identification=DEMO_WINDOWS)  # type: ignore[arg-type]
    )
    cold_url = sqlite_url(tmp_path, "cold.db")
    with served_service(database_url=cold_url, plan=COLD_THEN_WARM, settings=settings, feed_samples=30) as s:
        app = create_app(settings, s.service, clock=s.clock)
        with TestClient(app) as c:
            early = c.post(REF, headers=AUTH)  # 5 min after the start: the shaft's inside is not known yet
        assert early.status_code == 409 and "not known well enough" in early.text, early.text
        s.feed_next(REST_SAMPLES - 30)
        with LiveServer(app) as live:  # the CLI's own request, over loopback
            cold = zero(live.url, WRITE_TOKEN, temperature_c=None, set_by="tester")
    assert cold["source"] == "cli" and cold["set_by"] == "tester"
    assert abs(cold["temperature_c"] - 22.0) < 0.1 and 0.0 < cold["sd_c"] < 0.2
    # restart on the warm spindle (from 10 min into the machining), once with the stored zero, once without
    warm = per_condition(
        Settings(identification=DEMO_WINDOWS, compensation={"reference_on_first_start": True})  # type: ignore[arg-type]
    )
    axial = {}
    for name, db in (("stored", cold_url), ("none", sqlite_url(tmp_path, "empty.db"))):
        with served_service(database_url=db, plan=COLD_THEN_WARM, settings=warm, feed_samples=0) as s:
            for sample in s.samples[REST_SAMPLES + 60 :]:
                feed(s, sample)
            ref = s.service.compensation_reference()
            comp = s.service.compensation()
            assert comp is not None
            axial[name] = comp.growth.axial.um
            if name == "stored":
                assert ref is not None and ref.temperature_c == pytest.approx(cold["temperature_c"], abs=1e-4)
                assert ref.at == datetime.fromisoformat(str(cold["at"])) and ref.source == "cli"
                assert comp.growth.t_ref_c == pytest.approx(cold["temperature_c"], abs=1e-4)
                with s.persistence.session_factory() as session:  # the first start took none: one row
                    n = session.scalar(select(func.count()).select_from(CompensationReferenceRow))
                assert n == 1
            else:  # a warm first start takes no zero (the spindle turns): provisional, not usable
                assert ref is None and not comp.usable_for_compensation
                assert comp.reason is not None
    # the zero taken cold keeps the warm-up in the growth; a provisional zero on the warm spindle loses it
    assert axial["stored"] > 1.0
    assert axial["stored"] - axial["none"] > 0.5


def test_the_cli_reports_the_services_refusal_in_one_line() -> None:
    from service.commands._common import CommandError

    with pytest.raises(CommandError, match="cannot reach"):
        zero("http://127.0.0.1:9", WRITE_TOKEN, temperature_c=None, set_by="x", timeout_s=2.0)


def test_the_cli_says_why_the_service_refuses(served: object) -> None:
    from service.commands._common import CommandError

    app = create_app(Settings(api={"token": WRITE_TOKEN}), served.service, clock=served.clock)  # type: ignore[attr-defined]
    with LiveServer(app) as live:
        with pytest.raises(CommandError, match=r"\(409\).*turns") as refused:
            zero(live.url, WRITE_TOKEN, temperature_c=None, set_by="x")
        # the command's option, not the API's field (issue 41 item 5)
        assert "--temperature" in str(refused.value) and "temperature_c" not in str(refused.value)
        with pytest.raises(CommandError, match=r"\(403\)"):
            zero(live.url, "w" * 40, temperature_c=None, set_by="x")
