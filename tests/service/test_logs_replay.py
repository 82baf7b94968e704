"""``chtc identify`` on recorded logs is deterministic, and ``chtc replay`` of the same logs through the
simulated devices and the unchanged service gives the same identifications (up to sampling jitter)."""

from __future__ import annotations

import argparse
import asyncio
import json
from datetime import UTC, datetime, timedelta

import can
import numpy as np
import pytest

from drivers.can_codec import SPINDLE_STATUS_ID, encode_status
from drivers.logs import TemperatureCsvWriter, write_can_log
from model.plant import Segment
from service.cli import main as cli_main
from service.settings import Settings

from .conftest import plant_run

START = datetime(2026, 3, 2, 6, 0, 0, tzinfo=UTC)
PROFILE = [
    Segment(300.0, 0.0, 0.0, 22.0),
    Segment(1500.0, 3000.0, 5.0, 22.0),
    Segment(1500.0, 4000.0, 6.0, 22.0),
]


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    run = plant_run(PROFILE, seed=5, mesh_size_m=0.003)
    d = tmp_path_factory.mktemp("logs")
    csv_path, can_path = d / "temperatures.csv", d / "can.asc"
    with TemperatureCsvWriter(csv_path) as w:
        for k, t in enumerate(run.times_s):
            w.write(
                START + timedelta(seconds=float(t)),
                temps_c=run.temps_c[k],
                ambient_c=float(run.ambient_c[k]),
                status=run.status[k],
                counter=k,
            )
    frames = []
    for j, t in enumerate(np.arange(0.0, run.times_s[-1] + 1.0, 1.0)):
        k = min(int(t // 10), len(run.times_s) - 1)
        data = encode_status(float(run.speed_rpm[k]), float(run.torque_nm[k]), j % 16, 0)
        ts = (START + timedelta(seconds=float(t))).timestamp()
        frames.append(
            can.Message(timestamp=ts, arbitration_id=SPINDLE_STATUS_ID, data=data, is_extended_id=False)
        )
    write_can_log(can_path, frames)
    return csv_path, can_path


def _identify(logs, out):
    assert cli_main(["identify", str(logs[0]), str(logs[1]), "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_identify_is_deterministic_and_finds_both_conditions(logs, tmp_path, capsys):
    first = _identify(logs, tmp_path / "a.json")
    second = _identify(logs, tmp_path / "b.json")
    assert first == second
    ok = [r for r in first if r["outcome"] == "ok"]
    assert {round(r["condition"]["speed_rpm"], -2) for r in ok} == {3000, 4000}
    assert all(
        lo <= h <= hi
        for r in ok
        for h, lo, hi in zip(r["h_w_m2k"], r["ci95_lo_w_m2k"], r["ci95_hi_w_m2k"], strict=True)
    )
    printed = capsys.readouterr().out
    assert "H1=" in printed and "95 % CI" in printed
    # the log starts with 5 min at rest at the ambient: the offsets are zeroed against that baseline
    assert "sensor offsets: zeroed against a baseline at rest, 2026-03-02T06:00:00+00:00" in printed


def test_identify_names_a_bad_line(tmp_path, capsys, logs):
    bad = tmp_path / "bad.csv"
    lines = logs[0].read_text().splitlines()
    lines[5] = lines[5].replace(",", ";", 3)
    bad.write_text("\n".join(lines) + "\n")
    assert cli_main(["identify", str(bad)]) == 2
    assert "line 6" in capsys.readouterr().err


@pytest.mark.slow
def test_replay_gives_the_same_identifications_as_identify(logs, tmp_path):
    from service.commands.replay import run_replay

    offline = [r for r in _identify(logs, tmp_path / "offline.json") if r["outcome"] == "ok"]
    settings = Settings()
    settings = settings.model_copy(
        update={"database": settings.database.model_copy(update={"url": f"sqlite:///{tmp_path / 'r.db'}"})}
    )
    args = argparse.Namespace(csv=logs[0], can=logs[1], speedup=60.0, api=False, grace=30.0)
    replayed = [r for r in asyncio.run(run_replay(args, settings)) if r.outcome == "ok"]
    assert len(replayed) == len(offline) >= 4
    exact = 0
    for r, o in zip(replayed, offline, strict=True):
        assert r.condition.speed_rpm == pytest.approx(o["condition"]["speed_rpm"])
        assert (r.window_to - r.window_from).total_seconds() / 60 == pytest.approx(_minutes(o))
        exact += bool(np.allclose(r.h, o["h_w_m2k"], rtol=0.02, atol=0.2))
    # The replay samples each recorded row 0.3 periods after it: the same data, the same seeded fit, and the
    # same live state at every window start (a rebase replays from half a step before the window end, so a
    # job that finishes samples later, as in the running service, rebases exactly as offline, where it
    # finishes at once). The second condition's windows start from that rebased state.
    assert exact == len(offline), (
        exact,
        [(r.h, o["h_w_m2k"]) for r, o in zip(replayed, offline, strict=True)],
    )


def _minutes(o: dict) -> float:
    a = datetime.fromisoformat(o["window_from"])
    b = datetime.fromisoformat(o["window_to"])
    return (b - a).total_seconds() / 60
