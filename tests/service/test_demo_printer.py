"""``chtc demo``'s progress lines: the plant truth printed with an identification is the truth of the
identified window, not of the moment the line is printed (the plant may run at the next speed by then)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from types import SimpleNamespace

import numpy as np

from service.commands.demo import Printer

T0 = datetime(2026, 3, 2, 6, 0, tzinfo=UTC)


def _run() -> SimpleNamespace:
    times = np.arange(0.0, 7200.0, 10.0)
    speed = np.where(times < 3600.0, 3000.0, 4000.0)
    truth = np.where(times[:, None] < 3600.0, 1.0, 2.0) * np.arange(1.0, 8.0)
    return SimpleNamespace(times_s=times, speed_rpm=speed, h_true=truth)


def _printer(plant_now: float, record: SimpleNamespace) -> Printer:
    """The demo's printer at plant time ``plant_now`` [s], with ``record`` as the served identification."""
    printer = Printer(
        _run, quiet=False, clock=lambda: T0 + timedelta(seconds=plant_now), current=lambda: record
    )
    printer.rig = SimpleNamespace(plant_time_s=lambda: plant_now)
    return printer


def test_truth_is_the_identified_windows(capsys) -> None:
    plant_now = 3630.0  # 30 s into the 4000 rpm segment
    record = SimpleNamespace(window_from=T0 + timedelta(seconds=1200), window_to=T0 + timedelta(seconds=3600))
    printer = _printer(plant_now, record)
    printer("identification job-3 ok: H = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0] W/(m²·K), fit 0.97")
    out = capsys.readouterr().out
    assert "plant truth H = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0] (mid-window, 3000 rpm)" in out


def test_a_map_fits_truth_is_at_its_window_end(capsys) -> None:
    """A speed-map fit's window spans both speeds; its record holds the map at the launch condition (the
    window's end, 4000 rpm here), so that is where its truth is taken; its line carries no H, so the
    record's is printed."""
    plant_now = 3930.0
    record = SimpleNamespace(
        window_from=T0,
        window_to=T0 + timedelta(seconds=3900),
        method="speed-map",
        h=[2.1, 4.0, 6.0, 8.0, 10.0, 12.0, 14.5],
        condition=SimpleNamespace(speed_rpm=4000.0),
    )
    printer = _printer(plant_now, record)
    printer("map identification job-5 ok: 7 model runs, RMSE 0.107 °C, 0.18 s; visited 3 speed bins")
    out = capsys.readouterr().out
    assert "map H = [2.1, 4.0, 6.0, 8.0, 10.0, 12.0, 14.5] at 4000 rpm" in out
    want = "plant truth H = [2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0] (the map at the window's end, 4000 rpm)"
    assert want in out


def test_the_demo_rests_long_enough_for_an_offset_baseline() -> None:
    """Issue 42: a 5-min rest equal to the baseline's 5-min equilibrium window left the demo without an
    offset baseline for good, and its growth's CI at the 2 µm tolerance."""
    from service.cli import build_parser
    from service.commands.demo import demo_settings, idle_minutes

    args = build_parser(["demo"]).parse_args(["demo", "--port", "8765"])
    settings, _token = demo_settings(args, "sqlite:///:memory:")
    rest_s = settings.identification.offset_rest_s
    assert 60.0 * idle_minutes(args, settings) >= rest_s + 120.0
    short = build_parser(["demo"]).parse_args(["demo", "--port", "8765", "--idle-min", "2"])
    assert idle_minutes(short, settings) == 2.0


def test_a_map_fits_truth_is_at_the_speed_its_line_names(capsys) -> None:
    """Issue 41 item 10: a map fit launched at a condition change holds the map at the new condition (4000
    rpm), while the plant at the window's end still ran the old speed (3000 rpm); the truth line was printed
    for 3000 rpm under a map line at 4000 rpm. It is the plant's truth at the named speed: the first row of
    that speed from the window's end on."""
    plant_now = 3700.0
    record = SimpleNamespace(
        window_from=T0,
        window_to=T0 + timedelta(seconds=3590),  # 10 s before the plant reached 4000 rpm
        method="speed-map",
        h=[2.1, 4.0, 6.0, 8.0, 10.0, 12.0, 14.5],
        condition=SimpleNamespace(speed_rpm=4000.0),
    )
    printer = _printer(plant_now, record)
    printer("map identification job-6 ok: 7 model runs, RMSE 0.107 °C, 0.18 s; visited 3 speed bins")
    out = capsys.readouterr().out
    assert "map H = [2.1, 4.0, 6.0, 8.0, 10.0, 12.0, 14.5] at 4000 rpm" in out
    assert "plant truth H = [2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0] (the map at 4000 rpm" in out, out
