"""Ring buffer: wrap-around, window queries (checked against a brute-force filter), concurrent readers."""

from __future__ import annotations

import threading
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from drivers.errors import NoDataError, SampleOrderError
from drivers.quality import Quality
from drivers.ringbuffer import RingBuffer, Sample

T0 = datetime(2026, 1, 1, tzinfo=UTC)


def _sample(k: int, n: int = 4, *, dt_s: float = 10.0) -> Sample:
    q = np.full(n, k % 8, dtype=np.uint8)
    return Sample(
        T0 + timedelta(seconds=dt_s * k),
        np.full(n, float(k)),
        20.0 + k,
        1000.0 + k,
        0.5 * k,
        q,
        daq_ok=k % 2 == 0,
        can_ok=k % 3 != 0,
    )


def test_empty_buffer() -> None:
    ring = RingBuffer(5, n_channels=4)
    with pytest.raises(NoDataError):
        ring.latest()
    with pytest.raises(NoDataError):
        ring.time_span()
    w = ring.window(T0, T0 + timedelta(days=1))
    assert len(w) == 0 and w.temps_c.shape == (0, 4)


@pytest.mark.parametrize("n_appended", [3, 5, 7, 12, 23])
def test_wraparound_windows_match_brute_force(n_appended: int) -> None:
    cap = 5
    ring = RingBuffer(cap, n_channels=4)
    kept: list[Sample] = []
    for k in range(n_appended):
        s = _sample(k)
        ring.append(s)
        kept = [*kept, s][-cap:]
    assert len(ring) == min(n_appended, cap) and ring.appended == n_appended
    latest = ring.latest()
    assert latest.t == kept[-1].t and latest.speed_rpm == kept[-1].speed_rpm
    times = [s.t.timestamp() for s in kept]
    edges = [times[0] - 5, times[0], times[0] + 5, times[-1] - 10, times[-1], times[-1] + 1]
    for lo in edges:
        for hi in edges:
            w = ring.window(lo, hi)
            want = [s for s in kept if lo <= s.t.timestamp() <= hi]
            assert w.t.tolist() == [s.t.timestamp() for s in want]
            assert w.temps_c.tolist() == [s.temps_c.tolist() for s in want]
            assert w.speed_rpm.tolist() == [s.speed_rpm for s in want]
            assert w.quality.tolist() == [s.quality.tolist() for s in want]
            assert w.daq_ok.tolist() == [s.daq_ok for s in want] and w.can_ok.tolist() == [
                s.can_ok for s in want
            ]
    assert ring.time_span() == (times[0], times[-1])


def test_window_accepts_datetimes_and_returns_copies() -> None:
    ring = RingBuffer(10, n_channels=4)
    for k in range(10):
        ring.append(_sample(k))
    w = ring.window(T0 + timedelta(seconds=20), T0 + timedelta(seconds=40))
    assert [t.isoformat() for t in w.times_utc()] == [
        (T0 + timedelta(seconds=s)).isoformat() for s in (20, 30, 40)
    ]
    w.temps_c[:] = -1.0
    assert ring.window(T0, T0 + timedelta(seconds=20)).temps_c[-1, 0] == 2.0


def test_rejects_out_of_order_and_naive_times() -> None:
    ring = RingBuffer(4, n_channels=4)
    ring.append(_sample(5))
    with pytest.raises(SampleOrderError, match="earlier than the newest"):
        ring.append(_sample(4))
    with pytest.raises(ValueError, match="naive"):
        ring.window(datetime(2026, 1, 1), datetime(2026, 1, 2))


def test_append_values_default_quality_ok() -> None:
    ring = RingBuffer(4, n_channels=2)
    ring.append_values(100.0, [1.0, 2.0], ambient_c=20.0, speed_rpm=3000.0, torque_nm=1.0)
    s = ring.latest()
    assert s.quality.tolist() == [Quality.OK, Quality.OK] and s.t == datetime.fromtimestamp(100.0, UTC)


def test_concurrent_readers_see_consistent_rows() -> None:
    ring = RingBuffer(257, n_channels=32)
    n_writes = 20_000
    stop = threading.Event()
    problems: list[str] = []
    temps = np.empty(32)

    def writer() -> None:
        for k in range(n_writes):
            temps[:] = k  # every field of sample k is derived from k
            ring.append_values(
                float(k),
                temps,
                ambient_c=k,
                speed_rpm=k,
                torque_nm=-k,
                quality=np.full(32, k % 8, dtype=np.uint8),
            )
        stop.set()

    def reader() -> None:
        checks = 0
        while not stop.is_set() or checks < 50:
            checks += 1
            w = ring.window(-1.0, float(n_writes))
            if len(w) == 0:
                continue
            ok = (
                np.all(np.diff(w.t) == 1.0)
                and np.all(w.temps_c == w.t[:, None])
                and np.array_equal(w.speed_rpm, w.t)
                and np.array_equal(w.torque_nm, -w.t)
                and np.all(w.quality == (w.t.astype(int) % 8)[:, None])
            )
            if not ok:
                problems.append(f"inconsistent window ending at {w.t[-1]}")
            s = ring.latest()
            if not (np.all(s.temps_c == s.speed_rpm) and s.ambient_c == s.speed_rpm):
                problems.append(f"inconsistent latest sample {s.speed_rpm}")

    threads = [threading.Thread(target=reader) for _ in range(3)] + [threading.Thread(target=writer)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not problems, problems[:3]
    assert ring.latest().speed_rpm == n_writes - 1 and len(ring) == 257


def test_memory_for_a_day_at_one_hertz_is_modest() -> None:
    ring = RingBuffer(86_400, n_channels=32)
    nbytes = sum(a.nbytes for a in (ring._t, ring._temps, ring._quality, ring._ambient, ring._speed))
    assert nbytes < 40e6


@pytest.mark.parametrize("seed", range(5))
def test_random_capacities_gaps_and_equal_times_match_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cap = int(rng.integers(2, 40))
    ring = RingBuffer(cap, n_channels=2)
    t, stored = 0.0, []
    for k in range(int(rng.integers(1, 120))):
        t += float(rng.choice([0.0, 0.5, 1.0, 7.0]))  # equal timestamps allowed
        ring.append_values(t, [k, -k], ambient_c=k, speed_rpm=k, torque_nm=k)
        stored = [*stored, (t, k)][-cap:]
    for _ in range(30):
        lo, hi = sorted(rng.uniform(-1.0, t + 1.0, 2))
        w = ring.window(lo, hi)
        want = [k for (ts, k) in stored if lo <= ts <= hi]
        assert w.speed_rpm.tolist() == want
        assert w.temps_c[:, 1].tolist() == [-k for k in want]
