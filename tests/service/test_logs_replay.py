"""``chtc identify`` on recorded logs is deterministic, and ``chtc replay`` of the same logs through the
simulated devices and the unchanged service gives the same identifications (up to sampling jitter)."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import warnings
from datetime import UTC, datetime, timedelta

import can
import numpy as np
import pytest

from drivers.can_codec import SPINDLE_STATUS_ID, encode_status
from drivers.logs import TemperatureCsvWriter, write_can_log
from model.plant import Segment, h_true
from service.cli import main as cli_main
from service.commands.replay import GrowthLog
from service.contracts.verdict import ChtcStatus
from service.settings import Settings
from tests.timing import LoopLag

from .conftest import plant_run

START = datetime(2026, 3, 2, 6, 0, 0, tzinfo=UTC)
PROFILE = [
    Segment(300.0, 0.0, 0.0, 22.0),
    Segment(1500.0, 3000.0, 5.0, 22.0),
    Segment(1500.0, 4000.0, 6.0, 22.0),
]


PROFILE_RT = [  # one identification per condition, 7 min after its start (identification.schedule_min)
    Segment(300.0, 0.0, 0.0, 22.0),
    Segment(600.0, 3000.0, 5.0, 22.0),
    Segment(600.0, 4000.0, 6.0, 22.0),
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


@pytest.fixture(scope="module")
def realtime_logs(tmp_path_factory):
    """The same plant as ``logs`` recorded as ``chtc record`` does in real time: one row per second at a
    jittered receive time (each row with its own sensor noise), CAN frames every 0.1 s, also jittered.
    Shorter than ``logs``: 10-min conditions, one identification each (3 min before the next change or the
    end: the job's wall time at 30x is 30 recorded s per s), so the test can replay it at 30x (50 s; 15-min
    conditions took 70 s)."""
    run = plant_run(PROFILE_RT, seed=5, mesh_size_m=0.003)
    rng = np.random.default_rng(11)
    d = tmp_path_factory.mktemp("realtime")
    csv_path, can_path = d / "temperatures.csv", d / "can.blf"
    t_end = float(run.times_s[-1])
    with TemperatureCsvWriter(csv_path) as w:
        for j, t in enumerate(np.arange(0.4, t_end, 1.0)):
            k = min(int(t // 10), len(run.times_s) - 1)
            stamp = START + timedelta(seconds=float(t + rng.uniform(-0.3, 0.3)))
            temps = run.temps_c[k] + rng.normal(0.0, 0.05, size=run.temps_c.shape[1])
            w.write(stamp, temps_c=temps, ambient_c=float(run.ambient_c[k]), status=run.status[k], counter=j)
    frames = []
    for j, t in enumerate(np.arange(0.05, t_end, 0.1)):
        k = min(int(t // 10), len(run.times_s) - 1)
        data = encode_status(float(run.speed_rpm[k]), float(run.torque_nm[k]), j % 16, 0)
        ts = (START + timedelta(seconds=float(t + rng.uniform(0.0, 0.02)))).timestamp()
        frames.append(
            can.Message(timestamp=ts, arbitration_id=SPINDLE_STATUS_ID, data=data, is_extended_id=False)
        )
    write_can_log(can_path, frames)
    return csv_path, can_path


def _rewrite_csv(src, dst, *, keep=lambda t: True, scale=1.0):
    """A copy of a temperature CSV with only the rows ``keep(t_s after the first row)`` and times scaled."""
    from drivers.logs import read_temperature_csv

    log = read_temperature_csv(src)
    t0 = float(log.t_s[0])
    with TemperatureCsvWriter(dst) as w:
        for k in range(log.n_rows):
            rel = float(log.t_s[k]) - t0
            if keep(rel):
                stamp = datetime.fromtimestamp(t0 + scale * rel, tz=UTC)
                w.write(
                    stamp, temps_c=log.temps_c[k], ambient_c=float(log.ambient_c[k]), status=log.status[k]
                )
    return dst


def test_acquisition_ticks_follow_the_replay_grid() -> None:
    from drivers.logsamples import acquisition_ticks

    rows = np.array([100.2, 101.1, 102.3, 112.9, 125.0])
    ticks, idx = acquisition_ticks(rows, 100.0, period_s=10.0, phase=0.3)
    assert ticks.tolist() == pytest.approx([103.0, 113.0, 123.0])  # grid 100, 110, 120 (<= last row 125)
    assert idx.tolist() == [2, 3, 3]  # newest row at or before each tick
    ticks, idx = acquisition_ticks(rows, 95.0, period_s=10.0, phase=0.3)
    assert idx[0] == 0  # before the first row, the first row (as the replayed DAQ shows it)


def test_identify_without_a_can_log_says_what_is_missing(logs, capsys):
    assert cli_main(["identify", str(logs[0])]) == 2
    err = capsys.readouterr().err
    assert "no CAN log" in err and "--speed-rpm" in err and "Traceback" not in err


def test_identify_with_a_stated_speed_and_torque(logs, tmp_path, capsys):
    """Without a CAN log, a stated constant condition identifies (here the 3000 rpm part of the log)."""
    part = _rewrite_csv(logs[0], tmp_path / "t3000.csv", keep=lambda t: 300.0 <= t < 1800.0)
    out = tmp_path / "stated.json"
    argv = ["identify", str(part), "--speed-rpm", "3000", "--torque-nm", "5", "--json", str(out)]
    assert cli_main(argv) == 0
    ok = [r for r in json.loads(out.read_text()) if r["outcome"] == "ok"]
    assert ok and all(r["condition"]["speed_rpm"] == 3000.0 for r in ok)
    assert "stated 3000 rpm, 5 N·m" in capsys.readouterr().out


@pytest.mark.parametrize("mode", ["per_condition", "speed_map"])
def test_identify_says_why_nothing_was_identified(logs, tmp_path, capsys, monkeypatch, mode):
    """A sped-up simulation recorded with wall-time stamps: 55 min of plant squeezed into 55 s; the reason
    names what the mode's first identification needs."""
    monkeypatch.setenv("CHTC_IDENTIFICATION__MODE", mode)
    squeezed = _rewrite_csv(logs[0], tmp_path / "wall.csv", scale=1.0 / 60.0)
    assert cli_main(["identify", str(squeezed), "--speed-rpm", "3000", "--torque-nm", "5"]) == 1
    err = capsys.readouterr().err
    assert "nothing identified" in err and "the log covers 0.8 min" in err
    if mode == "per_condition":
        assert "needs 7.0 min of data at one condition" in err
    else:
        assert "the first map fit needs 10.0 min of data" in err and "map_min_window_min" in err
    assert "chtc record --speedup" in err


def _identify(logs, out):
    assert cli_main(["identify", str(logs[0]), str(logs[1]), "--json", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.mark.slow
def test_identify_is_deterministic_and_finds_both_conditions(logs, tmp_path, capsys):
    first = _identify(logs, tmp_path / "a.json")
    second = _identify(logs, tmp_path / "b.json")
    assert first == second
    ok = [r for r in first if r["outcome"] == "ok"]
    assert {round(r["condition"]["speed_rpm"], -2) for r in ok} == {3000, 4000}
    _assert_well_determined_h_covered(ok)
    printed = capsys.readouterr().out
    assert "H1=" in printed and "95 % CI" in printed
    # the log starts with 5 min at rest at the ambient: the offsets are zeroed against that baseline
    # (samples are taken half a period after each 10-s grid point, docs/design/service.md)
    assert "sensor offsets: zeroed against a baseline at rest, 2026-03-02T06:00:05+00:00" in printed


def test_identify_names_a_bad_line(tmp_path, capsys, logs):
    bad = tmp_path / "bad.csv"
    lines = logs[0].read_text().splitlines()
    lines[5] = lines[5].replace(",", ";", 3)
    bad.write_text("\n".join(lines) + "\n")
    assert cli_main(["identify", str(bad)]) == 2
    assert "line 6" in capsys.readouterr().err


def _check_growth_history(growth, replayed, offline, tmp_path):
    """The replay's growth history: what /compensation served, every minute and at each identification (time
    UTC, status of /chtc, axial/radial µm with CIs); at each identification it is the growth identify --json
    gives at the window end, within the CI, served when the replayed job finished: the job's wall time times
    the speed-up later (identify finishes at once), 2-6 min of recorded time at 60x on the shared box. The
    growth keeps changing meanwhile (a warm-up after a speed change), so that wait at the history's steepest
    rate is allowed on top of the CI."""
    rows = growth.rows
    at = [datetime.fromisoformat(r["at"]) for r in rows]
    assert len(rows) >= 10 and all(t.utcoffset() == timedelta(0) for t in at)
    assert at == sorted(at) and len(set(at)) == len(at)
    assert {r["status"] for r in rows} <= {s.value for s in ChtcStatus}
    assert {r["identification_id"] for r in rows} == {r.id for r in replayed}
    for r in rows:
        for part in ("axial", "radial", "steady_axial"):
            v = r[part]
            assert v["ci95_um"][0] < v["um"] < v["ci95_um"][1] and v["plc_0p1um"] == round(10 * v["um"])
    axial = np.array([r["axial"]["um"] for r in rows])
    steepest = float(np.max(np.abs(np.diff(axial)) / np.diff([t.timestamp() for t in at])))  # µm/s
    for r, o in zip(replayed, offline, strict=True):
        first = growth.by_id[r.id]
        wait_s = (datetime.fromisoformat(first["at"]) - r.window_to).total_seconds()
        assert wait_s >= 0
        want = o["growth"]["axial"]
        half = 0.5 * (want["ci95_um"][1] - want["ci95_um"][0])
        allowed = half + steepest * wait_s
        assert abs(first["axial"]["um"] - want["um"]) < allowed, (first, want, wait_s, steepest)
    out = tmp_path / "replayed.csv"
    growth.write(out)
    lines = out.read_text().splitlines()
    assert len(lines) == len(rows) + 1 and lines[0].startswith("at,status,usable_for_compensation")


def _stall_budget_s(settings: Settings, speedup: float) -> float:
    """The longest event-loop stall a replay at ``speedup`` absorbs, wall s (docs/design/service.md, "Replay =
    identify"): a sample sees its own row while the stall ends before the row's half period is over, less
    one DAQ poll interval (the last poll before the stall may be that old)."""
    period = settings.acquisition.sample_period_s
    poll = min(settings.modbus.poll_interval_s, period / 2.0)
    return (period / 2.0 - poll) / speedup


async def _replay_probed(args, settings, growth, monkeypatch):
    """``run_replay`` with a ``LoopLag`` probe in its event loop: the records and how late the loop ran from
    the replay's first row on (the start-up before it, a database migration and a worker process spawned on
    the loop, is no replay)."""
    from drivers.sim.replay import Replay
    from service.commands.replay import run_replay

    lag = LoopLag()
    begin = Replay.begin

    def begin_probed(self: Replay) -> None:
        lag.late_s.clear()
        begin(self)

    monkeypatch.setattr(Replay, "begin", begin_probed)
    probe = asyncio.create_task(lag.run())
    try:
        return await run_replay(args, settings, growth=growth), lag
    finally:
        probe.cancel()


def _replay_paced(logs, tmp_path, monkeypatch, check, *, speedups):
    """Replay ``logs`` at the first pace of ``speedups`` and ``check(replayed ok records, growth log)``.

    A replay keeps wall time; a replay whose event loop kept time (no stall beyond ``_stall_budget_s``) must
    pass, so a failure then is a real difference. A failure after a longer stall (the shared 2-core box at
    load 10-15 stalls a process for a few hundred ms now and then) is the machine's, not the replay's: the
    test replays again at the next, slower pace, which absorbs longer stalls. If the slowest pace stalled
    beyond its budget too, the test cannot judge: it is skipped naming the stalls (failed in CI)."""
    seen: list[str] = []
    for i, speedup in enumerate(speedups):
        settings = Settings()
        url = f"sqlite:///{tmp_path / f'r{i}.db'}"
        settings = settings.model_copy(update={"database": settings.database.model_copy(update={"url": url})})
        args = argparse.Namespace(csv=logs[0], can=logs[1], speedup=speedup, api=False, grace=30.0)
        growth = GrowthLog()
        records, lag = asyncio.run(_replay_probed(args, settings, growth, monkeypatch))
        budget = _stall_budget_s(settings, speedup)
        try:
            check([r for r in records if r.outcome == "ok"], growth)
            if seen:
                warnings.warn(f"replay = identify at {speedup:g}x after {'; '.join(seen)}", stacklevel=2)
            return
        except AssertionError as err:
            seen.append(
                f"{speedup:g}x: stall {1e3 * lag.max_s:.0f} ms (absorbs {1e3 * budget:.0f} ms): {err!r:.300}"
            )
            if lag.max_s <= budget:
                raise AssertionError(f"the replay kept time and differs; {'; '.join(seen)}") from err
            if i == len(speedups) - 1:
                why = f"too loaded to judge replay = identify (docs/design/service.md); {'; '.join(seen)}"
                if os.environ.get("CI", "").lower() == "true":  # as tests/conftest.py's missing services
                    raise AssertionError(why) from err
                pytest.skip(why)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_replay_gives_the_same_identifications_as_identify(logs, tmp_path, monkeypatch):
    # Per condition (combined and speed-map mode: a map fit's H reaches the live state at the first sample
    # after the worker returns it, and the map's bookkeeping depends on that; the full suite under load once
    # saw one fit fewer in the replay than offline).
    monkeypatch.setenv("CHTC_IDENTIFICATION__MODE", "per_condition")

    offline = [r for r in _identify(logs, tmp_path / "offline.json") if r["outcome"] == "ok"]

    def check(replayed, growth):
        assert len(replayed) == len(offline) >= 4
        _check_growth_history(growth, replayed, offline, tmp_path)
        first_condition = offline[0]["condition"]["id"]
        for r, o in zip(replayed, offline, strict=True):
            assert r.condition.speed_rpm == pytest.approx(o["condition"]["speed_rpm"])
            assert (r.window_from, r.window_to) == tuple(
                datetime.fromisoformat(o[k]) for k in ("window_from", "window_to")
            )  # the sample stamps are identify's (GridClock)
            h, lo, hi = (np.asarray(o[k]) for k in ("h_w_m2k", "ci95_lo_w_m2k", "ci95_hi_w_m2k"))
            if o["condition"]["id"] == first_condition:
                # the same samples, the same start state (no earlier job's H in it), the same seeded fit
                allowed = 0.02 * h + 0.2
            else:
                # a later condition's windows start from the live state, which took the previous condition's H
                # when the worker returned it: the job's wall time times the speed-up after the window end
                # (offline: at once; the filtered state has no rebase, docs/design/service.md). The identified
                # H equal; a poorly identified one (the fit is flat along it) within 5 % of its CI width
                # (measured at 20x, load 9: H1 74.6 and 110.0 against 67.3 and 102.8, CI widths 3e5 and 4e3;
                # every identified H within 0.2 %)
                allowed = np.where(
                    o["identified"], 0.02 * h + 0.2, np.maximum(0.02 * h + 0.2, 0.05 * (hi - lo))
                )
            assert np.all(np.abs(np.asarray(r.h) - h) <= allowed), (o["id"], r.h, h.tolist(), o["identified"])

    # 60x absorbs a stall of 67 ms (55 s of replay), 20x one of 200 ms (165 s)
    _replay_paced(logs, tmp_path, monkeypatch, check, speedups=(60.0, 20.0))


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_replay_reproduces_identify_for_a_realtime_recording(realtime_logs, tmp_path, monkeypatch):
    """One jittered row per second (as chtc record writes): replay used to sample rows one poll apart from
    identify's, and identify fed every row as a sample, so windows and H differed (13 s and H1 52 vs 200).
    Per-condition mode, as the test above (one identification per 10-min condition)."""
    monkeypatch.setenv("CHTC_IDENTIFICATION__MODE", "per_condition")  # chtc identify's settings
    offline = [r for r in _identify(realtime_logs, tmp_path / "offline.json") if r["outcome"] == "ok"]

    def check(replayed, growth):
        assert len(replayed) == len(offline) == 2
        for r, o in zip(replayed, offline, strict=True):
            assert (r.window_from, r.window_to) == tuple(
                datetime.fromisoformat(o[k]) for k in ("window_from", "window_to")
            )  # the sample stamps are identify's (GridClock)
            h, lo, hi = (np.asarray(o[k]) for k in ("h_w_m2k", "ci95_lo_w_m2k", "ci95_hi_w_m2k"))
            # identified H equal; a poorly identified one (CI half-width > 50 %: the fit is flat along it,
            # and a worker process's floating point or one sample delayed by a stall moves it) within 5 % of
            # its CI
            allowed = np.where(o["identified"], 0.02 * h + 0.2, np.maximum(0.02 * h + 0.2, 0.05 * (hi - lo)))
            assert np.all(np.abs(np.asarray(r.h) - h) <= allowed), (r.h, h.tolist(), o["identified"])

    # 30x absorbs a stall of 133 ms (50 s of replay), 10x one of 400 ms (150 s)
    _replay_paced(realtime_logs, tmp_path, monkeypatch, check, speedups=(30.0, 10.0))


def _assert_well_determined_h_covered(records: list[dict]) -> None:
    """The 95 % CIs of H6 and H7, the two best-determined H, cover the virtual plant's truth at the record's
    condition (``model.plant.h_true``; both recordings come from the plant at a constant 22 °C ambient).

    What the offline bench establishes: ``python -m benchmarks chain --seeds 20`` (the service core over 20
    plant noise seeds, three chained conditions, 2026-11-24) covered H6 and H7 in 20 of 20 seeds at each of
    3000, 4000 and 5000 rpm (median |error| 3.7-4.5 % for H6, 7.7-15.4 % for H7). These windows are shorter
    (10-20 min instead of 40), so the CIs are wider; a miss is allowed nowhere, since the nominal level (5 %
    per H) and the bench's 0 misses in 120 seed-condition-H trials make one unlikely, and ``chtc identify`` is
    deterministic for a given recording (a miss is a change of the numbers, not bad luck)."""
    for r in records:
        c = r["condition"]
        truth = h_true(c["speed_rpm"], c["ambient_c"])[5:]
        lo, hi = np.asarray(r["ci95_lo_w_m2k"])[5:], np.asarray(r["ci95_hi_w_m2k"])[5:]
        assert np.all((lo <= truth) & (truth <= hi)), (c, lo, hi, truth)


@pytest.mark.slow  # over ~5 s alone (issue 25: the fast subset under 5 min)
@pytest.mark.parametrize("mode", ["per_condition", "speed_map"])
def test_identify_on_the_shipped_example_recording(tmp_path, capsys, monkeypatch, mode):
    """README's first step: the recording under service/data (made with chtc simulate + chtc record
    --speedup 10) identifies both conditions, in either mode. In per-condition mode the CIs of H6 and H7
    cover the plant's truth; in speed-map mode the first map (10 min from a cold start) has an H7 band that
    misses it (H7 4.3 [1.3, 14.4] against 16.7, docs/design/hmap.md "Measured: restart": the first map's H6/H7
    bands from a cold start), so only the later maps are held to it."""
    from pathlib import Path

    monkeypatch.setenv("CHTC_IDENTIFICATION__MODE", mode)
    data = Path(__file__).resolve().parents[2] / "service" / "data"
    out = tmp_path / "example.json"
    argv = ["identify", str(data / "example_temperatures.csv"), str(data / "example_can.blf")]
    assert cli_main([*argv, "--json", str(out)]) == 0
    assert f"({mode}, seed 0)" in capsys.readouterr().out
    ok = [r for r in json.loads(out.read_text()) if r["outcome"] == "ok"]
    assert {r["condition"]["speed_rpm"] for r in ok} == {3000.0, 4000.0}
    # made by chtc simulate --profile service/data/example_profile.toml (docs/design/simulation.md):
    # plant truth
    _assert_well_determined_h_covered(ok if mode == "per_condition" else ok[1:])


def test_the_sampler_keeps_its_phase_after_a_stall() -> None:
    """A stall of more than a period used to restart the ticks from the end of the stall (a new phase), so
    every later sample of a replay saw other rows than identify's; now missed ticks are skipped in phase."""
    from drivers.acquisition import Acquisition
    from drivers.errors import NoDataError
    from drivers.ringbuffer import RingBuffer

    now = [0.0]
    stalls = {3: 2.5}  # the 3rd sleep returns 2.5 periods late

    class Silent:
        def current(self):
            raise NoDataError("nothing yet")

    async def sleep(dt: float) -> None:
        n = len(ticks) + 1
        now[0] += dt + stalls.get(n, 0.0) * 10.0
        if n > 8:
            raise asyncio.CancelledError

    ticks: list[float] = []
    acq = Acquisition(
        Silent(),  # type: ignore[arg-type]
        Silent(),  # type: ignore[arg-type]
        RingBuffer(100, 32),
        period_s=10.0,
        on_sample=lambda s: ticks.append(now[0]),
        clock=lambda: now[0],
        now=lambda: datetime.fromtimestamp(now[0], tz=UTC),
        sleep=sleep,
    )
    with pytest.raises(asyncio.CancelledError):
        asyncio.run(acq.run_sampler())
    assert ticks[3:] and all(t % 10.0 == pytest.approx(0.0) for t in ticks[3:]), ticks
