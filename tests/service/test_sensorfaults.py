"""The stuck/drift channel monitor (service.estimate.sensorfaults) on synthetic checks: a prediction that
follows a smooth truth, readings with the DAQ's noise (σ 0.15 °C, 0.01 °C quantum), one channel faulted."""

from __future__ import annotations

import numpy as np
import pytest

from service.estimate.sensorfaults import (
    FaultKind,
    FaultMonitor,
    FaultMonitorSettings,
    SensorFaultError,
    fault_lines,
)

N = 32
DT_S = 10.0
SIGMA = 0.15
STD = 0.17  # √S: the noise and the state's own 1σ at the sensors


def truth(k: int) -> np.ndarray:
    """A warming spindle: 32 channels rising towards 5–12 °C over the ambient, with a slow wobble."""
    t_h = k * DT_S / 3600.0
    rise = np.linspace(5.0, 12.0, N)
    return 22.0 + rise * (1.0 - np.exp(-t_h / 0.7)) + 0.3 * np.sin(2 * np.pi * t_h / 1.5)


def run(
    monitor: FaultMonitor,
    n: int,
    *,
    seed: int = 0,
    fault: tuple[int, str, int] | None = None,
    offsets: np.ndarray | None = None,
    absorb: float = 0.3,
    recover_at: int | None = None,
) -> list[tuple[int, str, int, bool]]:
    """Push ``n`` samples; ``fault`` = (index, "stuck"|"drift", start sample), drift +0.5 °C/h; the prediction
    follows a faulted reading by ``absorb`` of its error while the channel is used (the filter bends to it).
    Returns (sample, kind, index, recovered) per change."""
    rng = np.random.default_rng(seed)
    off = np.zeros(N) if offsets is None else offsets
    out: list[tuple[int, str, int, bool]] = []
    frozen = None
    for k in range(n):
        true = truth(k)
        y = np.round((true + off + SIGMA * rng.standard_normal(N)) / 0.01) * 0.01
        err = np.zeros(N)
        if fault is not None and k >= fault[2] and (recover_at is None or k < recover_at):
            i, kind, start = fault
            if kind == "stuck":
                frozen = y[i] if frozen is None else frozen
                y[i] = frozen
            else:
                y[i] += 0.5 * (k - start) * DT_S / 3600.0
            err[i] = y[i] - off[i] - true[i]
        used = ~monitor.excluded()
        pred = true + np.where(used, absorb * err, 0.0)
        for ch in monitor.observe(k * DT_S, y, np.ones(N, bool), pred, np.full(N, STD), off):
            out.append((k, ch.fault.kind.value, ch.fault.index, ch.recovered))
    return out


@pytest.mark.slow
def test_clean_data_over_eight_hours_raise_no_alarm() -> None:
    for seed in range(3):
        m = FaultMonitor(N, noise_c=SIGMA)
        assert run(m, 8 * 360, seed=seed) == []
        assert m.active() == ()


def test_constant_offsets_without_a_baseline_are_not_a_drift() -> None:
    """±0.2 °C offsets no baseline removed (the prediction in the offset-corrected frame misses them)."""
    off = np.random.default_rng(9).uniform(-0.2, 0.2, N)
    m = FaultMonitor(N, noise_c=SIGMA)
    # the monitor is told no offsets (none known): the readings sit off the prediction by them for good
    rng = np.random.default_rng(1)
    for k in range(4 * 360):
        y = truth(k) + off + SIGMA * rng.standard_normal(N)
        assert m.observe(k * DT_S, y, np.ones(N, bool), truth(k), np.full(N, STD)) == []


def test_a_stuck_channel_is_found_within_its_window_and_taken_back_when_it_moves() -> None:
    m = FaultMonitor(N, noise_c=SIGMA)
    changes = run(m, 4 * 360, fault=(7, "stuck", 600), recover_at=900)
    found = [c for c in changes if not c[3]]
    assert found[0][1:3] == ("stuck", 7)
    assert found[0][0] - 600 <= FaultMonitorSettings().stuck_window + 1  # 5 min, bar: 30 min
    back = [c for c in changes if c[3]]
    assert back and back[0][2] == 7 and 900 < back[0][0] <= 900 + 2 * FaultMonitorSettings().recover_window
    assert m.active() == ()


@pytest.mark.slow
def test_a_drift_is_found_before_it_reaches_one_degree_and_stays_out() -> None:
    for seed in range(5):
        m = FaultMonitor(N, noise_c=SIGMA)
        changes = run(m, 6 * 360, seed=seed, fault=(20, "drift", 400))
        assert changes, f"seed {seed}: not found"
        k, kind, index, recovered = changes[0]
        assert (kind, index, recovered) == ("drift", 20, False)
        drift_c = 0.5 * (k - 400) * DT_S / 3600.0
        assert drift_c < 1.0, f"seed {seed}: found at {drift_c:.2f} °C"
        assert len(changes) == 1  # still drifting: never taken back
        (fault,) = m.active()
        assert fault.channel == 21 and fault.since_t == k * DT_S and "drifting +" in fault.detail


def test_a_drift_that_ends_back_at_zero_is_taken_back() -> None:
    m = FaultMonitor(N, noise_c=SIGMA)
    changes = run(m, 5 * 360, fault=(3, "drift", 400), recover_at=1000)
    assert [c[3] for c in changes] == [False, True]
    assert m.excluded().sum() == 0


def test_many_channels_at_once_are_the_models_problem_not_the_sensors() -> None:
    m = FaultMonitor(N, noise_c=SIGMA, settings=FaultMonitorSettings(max_excluded=2))
    rng = np.random.default_rng(3)
    for k in range(3 * 360):
        y = truth(k) + SIGMA * rng.standard_normal(N)
        y[:6] = 30.0  # six channels frozen
        m.observe(k * DT_S, y, np.ones(N, bool), truth(k), np.full(N, STD))
    assert m.excluded().sum() == 2


def test_channels_the_daq_flags_are_not_judged() -> None:
    m = FaultMonitor(N, noise_c=SIGMA)
    ok = np.ones(N, bool)
    ok[5] = False
    for k in range(200):
        y = truth(k) + SIGMA * np.random.default_rng(k).standard_normal(N)
        y[5] = 1e3
        assert m.observe(k * DT_S, y, ok, truth(k), np.full(N, STD)) == []


def test_bad_input_names_the_field() -> None:
    m = FaultMonitor(N)
    with pytest.raises(SensorFaultError, match="predicted_c"):
        m.observe(0.0, np.zeros(N), np.ones(N, bool), np.zeros(3), np.ones(N))
    with pytest.raises(SensorFaultError, match="ok"):
        m.observe(0.0, np.zeros(N), np.ones(3, bool), np.zeros(N), np.ones(N))
    with pytest.raises(SensorFaultError, match="cusum_h"):
        FaultMonitorSettings(cusum_h=0.0)
    with pytest.raises(SensorFaultError, match="channels"):
        FaultMonitor(N, channels=(1, 2))
    assert FaultKind("stuck") is FaultKind.STUCK


def test_identification_windows_leave_out_what_a_fault_touched_and_the_log_says_it() -> None:
    """A stuck channel is suspect from its frozen window's start; once taken back, windows after that are
    clean again. The log names channel, kind, since when (UTC) and why, then the recovery."""
    m = FaultMonitor(N, noise_c=SIGMA)
    changes: list[str] = []
    rng = np.random.default_rng(4)
    frozen = 0.0
    for k in range(1200):
        y = np.round((truth(k) + SIGMA * rng.standard_normal(N)) / 0.01) * 0.01
        frozen = y[2] if k == 300 else frozen
        if 300 <= k < 500:
            y[2] = frozen
        got = m.observe(k * DT_S, y, np.ones(N, bool), truth(k), np.full(N, STD))
        changes += fault_lines(got)
        if 340 <= k < 500:
            assert m.suspect(0.0, k * DT_S)[2] and m.excluded()[2]
    assert not m.excluded()[2]
    assert m.suspect(2900.0, 3050.0)[2]  # overlaps the frozen window (found at 3300 s, 31 samples back)
    assert not m.suspect(2000.0, 2500.0)[2]  # before it
    assert not m.suspect(11000.0, 11900.0)[2]  # after it was taken back
    assert len(changes) == 2
    assert changes[0].startswith("sensor channel 3 left out of the live state as stuck since 1970-01-01T")
    assert f"frozen at {frozen:.2f} °C" in changes[0]
    assert changes[1].startswith("sensor channel 3 taken back into the live state at ")


def test_a_drift_is_suspect_for_identification_windows_before_its_alarm() -> None:
    """A CUSUM past half its threshold leaves the channel out of identification windows (not yet out of the
    live state's updates): the windows taken while a drift grows unseen no longer carry it."""
    m = FaultMonitor(N, noise_c=SIGMA)
    rng = np.random.default_rng(6)
    first_suspect = found = None
    for k in range(3 * 360):
        true = truth(k)
        y = true + SIGMA * rng.standard_normal(N)
        if k >= 400:
            y[20] += 0.5 * (k - 400) * DT_S / 3600.0
        used = ~m.excluded()
        pred = true + np.where(used, 0.3 * (y - true) * (np.arange(N) == 20), 0.0)
        m.observe(k * DT_S, y, np.ones(N, bool), pred, np.full(N, STD))
        if first_suspect is None and m.suspect(0.0, k * DT_S)[20]:
            first_suspect = k
        if found is None and m.excluded()[20]:
            found = k
        others = m.suspect(0.0, k * DT_S)
        others[20] = False
        assert not others.any(), f"sample {k}: clean channels suspect {np.flatnonzero(others)}"
    assert first_suspect is not None and found is not None
    assert 400 < first_suspect < found  # suspect before the alarm
    assert m.excluded()[20]  # by the end it is out of the live state's updates too
    with pytest.raises(SensorFaultError, match="suspect_cusum_frac"):
        FaultMonitorSettings(suspect_cusum_frac=0.0)
