"""``python -m benchmarks acquisition``: Modbus poll latency, CAN decode rate, ring buffer, reconnect time,
CPU load.

Figures (targets in brackets):

- ``modbus_poll_ms_median`` / ``_p99`` [median <= 1 ms]: one full poll (33 temperatures + status + counter,
  three FC4 requests) with ``drivers.modbus_daq.ModbusDaq`` against the simulated DAQ running in a separate
  process on loopback; peer: the same three requests with a bare pymodbus client (``raw_poll_ms_median``).
  ``modbus_poll_ms_median_same_process``: the same with the simulator on the same event loop (no
  cross-process wake-ups; less sensitive to a busy machine, but the server's work is included).
- ``can_frames_per_s`` [>= 10 000 with ``can_frames_lost`` = 0]: ``SpindleStatus`` frames sent by a
  thread on a ``virtual`` bus in this process at fixed rates (``--can-rates``, ``--can-seconds`` each) and
  decoded by ``drivers.can_sensor.CanSpindleSensor``. A rate is *sustained* when every frame is decoded, the
  rolling counter has no gap and at least 95 % of the rate is decoded per second from the first send to the
  last decode (the virtual bus queues without limit, so "no loss" alone would hide a decoder that falls
  behind; a sender slowed by a busy machine also fails). The figure is the
  decoded rate (frames / s from the first send to the last decode) at the highest sustained rate;
  ``can_first_unsustained_rate_per_s`` is the next rate tried (0: all sustained); ``can_frames_lost`` counts
  frames not decoded or missing by counter in the sustained runs (a minority of runs may lose some). The
  target is judged on the sustained offered rate (the decoded rate includes the pipeline's tail).
  Also a burst of ``--can-burst`` frames sent as fast as the thread can (``can_burst_frames_per_s``,
  ``can_burst_lost``; sender and decoder then compete for the GIL) against a bare ``bus.recv`` +
  ``decode_frame`` loop (``raw_can_frames_per_s``, the peer).
- ``ring_append_us`` and ``ring_window_ms``: ``drivers.ringbuffer.RingBuffer`` append of one 32-channel
  sample, and copying a 60-min window at 1 Hz (3600 samples) out of a 2-hour buffer.
- ``reconnect_s`` [<= 2 s]: the simulated DAQ drops every connection and refuses new ones for
  ``--outage-s`` (default 10 s); time from its return to the driver's first good reading (poll every 0.1 s),
  median (and ``reconnect_s_max``) over ``--repeats`` outages. It depends on where in the driver's backoff
  (at most 2 s) the device returns, hence the spread.
- ``cpu_pct_10hz`` [< 5 % of one core]: ``time.process_time`` of this process over ``--cpu-s`` seconds of
  ``drivers.acquisition.Acquisition`` polling the DAQ at 10 Hz and receiving CAN at 100 Hz through the
  python-can-remote hub (both devices simulated in the other process), sampling at 1 Hz; also each part
  alone (``cpu_pct_modbus_only``, ``cpu_pct_can_only``). ``cpu_pct_10hz_local_can``: the same with CAN on
  an in-process ``virtual`` bus fed by a 100 Hz sender thread whose own CPU time is subtracted, which is
  closer to production (socketcan: frames come from the kernel, no WebSocket client in the process).
  ``cpu_pct_10hz_can_batch_50ms``: as ``cpu_pct_10hz`` with the CAN driver's ``batch_s=0.05``.

Medians are over ``--repeats`` runs where a figure is measured repeatedly. The machine is shared, so the
p99 figures carry scheduler noise.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import multiprocessing as mp
import os
import statistics
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from multiprocessing.connection import Connection
from typing import Any

import can
import numpy as np
from pymodbus.client import AsyncModbusTcpClient

from drivers.acquisition import Acquisition
from drivers.can_codec import SPINDLE_STATUS_ID, decode_frame, encode_status
from drivers.can_sensor import BATCH_S, CanSpindleSensor
from drivers.errors import DeviceError
from drivers.modbus_daq import ModbusDaq
from drivers.ringbuffer import RingBuffer, Sample
from drivers.sim.can_hub import CanHub
from drivers.sim.can_node import SimulatedCanNode
from drivers.sim.faults import FaultController, FaultKind
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import ArrayTimeline, TimelineSource

TARGETS = {
    "modbus_poll_ms_median": ("<=", 1.0),
    "can_frames_per_s": (">=", 10_000.0),
    "reconnect_s": ("<=", 2.0),
    "cpu_pct_10hz": ("<", 5.0),
}


# --------------------------------------------------------------------------------- devices in a process
def _timeline() -> ArrayTimeline:
    base = 20.0 + 0.25 * np.arange(32)
    return ArrayTimeline(
        times_s=np.array([0.0, 3600.0]),
        temps_c=np.vstack([base, base + 15.0]),
        ambient_c=np.array([21.0, 22.0]),
        speed_rpm=np.array([3000.0, 5000.0]),
        torque_nm=np.array([5.0, 8.0]),
        status=np.zeros((2, 32), dtype=np.int64),
    )


def _device_process(conn: Connection) -> None:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # injected outages make pymodbus log noisily
    asyncio.run(_device_main(conn))


async def _device_main(conn: Connection) -> None:
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    hub = CanHub("ws://127.0.0.1:0/", channel=channel)
    hub.start()
    bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    source = TimelineSource(_timeline(), speedup=1.0, loop=True)
    faults = FaultController()
    try:
        async with (
            SimulatedDaq(source, port=0, faults=faults) as daq,
            SimulatedCanNode(source, bus=bus, faults=faults),
        ):
            conn.send(("ready", daq.port, hub.url))
            while True:
                command, kind = await asyncio.to_thread(conn.recv)
                if command == "stop":
                    break
                if command == "inject":
                    faults.inject(kind)
                else:
                    faults.clear(kind)
                conn.send(("ok", command, kind))
    finally:
        bus.shutdown()
        hub.stop()


class Devices:
    """The simulated DAQ and CAN hub in a child process; ``inject``/``clear`` faults over a pipe."""

    def __init__(self, conn: Connection, port: int, hub_url: str) -> None:
        self.conn, self.port, self.hub_url = conn, port, hub_url

    def command(self, command: str, kind: str) -> None:
        """Send a fault command and wait for the acknowledgement."""
        self.conn.send((command, kind))
        self.conn.recv()


@contextmanager
def devices() -> Iterator[Devices]:
    """Start the device process, yield a handle, stop it."""
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_device_process, args=(child,), daemon=True)
    proc.start()
    try:
        if not parent.poll(60):
            raise RuntimeError("device process did not start within 60 s")
        _, port, url = parent.recv()
        yield Devices(parent, port, url)
        parent.send(("stop", ""))
    finally:
        proc.join(5)
        if proc.is_alive():
            proc.terminate()


# ----------------------------------------------------------------------------------------------- Modbus
async def _poll_times(port: int, n: int) -> tuple[list[float], list[float]]:
    daq = ModbusDaq("127.0.0.1", port, timeout_s=1.0)
    raw = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=1.0, retries=0, reconnect_delay=0)
    await raw.connect()
    driver_ms, raw_ms = [], []
    try:
        for _ in range(20):
            await daq.read()
        for _ in range(n):
            t = time.perf_counter()
            await daq.read()
            driver_ms.append((time.perf_counter() - t) * 1e3)
            t = time.perf_counter()
            for start, count in daq.blocks:
                await raw.read_input_registers(start, count=count, device_id=1)
            raw_ms.append((time.perf_counter() - t) * 1e3)
    finally:
        await daq.close()
        raw.close()
    return driver_ms, raw_ms


async def _poll_times_in_process(n: int) -> list[float]:
    source = TimelineSource(_timeline(), loop=True)
    async with SimulatedDaq(source, port=0) as sim:
        driver_ms, _ = await _poll_times(sim.port, n)
    return driver_ms


def bench_modbus(dev: Devices, *, polls: int, repeats: int) -> dict[str, float]:
    """Median and p99 of one full poll (ms), medians over repeats; bare pymodbus as the peer."""
    med, p99, raw, inproc = [], [], [], []
    for _ in range(repeats):
        driver_ms, raw_ms = asyncio.run(_poll_times(dev.port, polls))
        med.append(statistics.median(driver_ms))
        p99.append(float(np.percentile(driver_ms, 99)))
        raw.append(statistics.median(raw_ms))
        inproc.append(statistics.median(asyncio.run(_poll_times_in_process(polls))))
    return {
        "modbus_poll_ms_median_same_process": statistics.median(inproc),
        "modbus_poll_ms_median": statistics.median(med),
        "modbus_poll_ms_p99": statistics.median(p99),
        "raw_poll_ms_median": statistics.median(raw),
        "modbus_driver_vs_raw": statistics.median(med) / statistics.median(raw),
    }


# -------------------------------------------------------------------------------------------------- CAN
def _frames(n: int) -> list[can.Message]:
    return [
        can.Message(
            arbitration_id=SPINDLE_STATUS_ID, is_extended_id=False, data=encode_status(3000, 5.0, i % 16, 0)
        )
        for i in range(n)
    ]


def _send_paced(bus: can.BusABC, frames: list[can.Message], rate_per_s: float) -> None:
    """Send ``frames`` at ``rate_per_s`` (in chunks of 1 ms worth, deadline-paced, no drift)."""
    chunk = max(1, int(rate_per_s / 1000))
    t0 = time.perf_counter()
    for i in range(0, len(frames), chunk):
        for m in frames[i : i + chunk]:
            bus.send(m)
        delay = t0 + (i + chunk) / rate_per_s - time.perf_counter()
        if delay > 0:
            time.sleep(delay)


@dataclass(frozen=True, kw_only=True)
class CanRun:
    """One CAN rate run: frames offered, decoded, missing by counter; send and decode durations (s)."""

    offered: int
    decoded: int
    gap_frames: int
    send_s: float
    decode_s: float

    @property
    def rate_per_s(self) -> float:
        """Decoded frames per second of wall time since the first frame was sent."""
        return self.decoded / max(self.decode_s, 1e-9)

    def sustained(self, nominal_per_s: float) -> bool:
        """No frame lost and >= 95 % of ``nominal_per_s`` decoded per second (a slow sender fails too)."""
        lossless = self.decoded == self.offered and self.gap_frames == 0
        return lossless and self.rate_per_s >= 0.95 * nominal_per_s


async def _driver_run(frames: list[can.Message], rate_per_s: float | None) -> CanRun:
    """Send ``frames`` at ``rate_per_s`` (None: as fast as possible) and decode them with the CAN driver."""
    channel = f"rate-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    rx = can.Bus(interface="virtual", channel=channel, ignore_config=True)  # queues frames from now on
    sensor = CanSpindleSensor(bus=rx, stale_after_s=1.0)
    sent_at: list[float] = []

    def send() -> None:
        if rate_per_s is None:
            for m in frames:
                tx.send(m)
        else:
            _send_paced(tx, frames, rate_per_s)
        sent_at.append(time.perf_counter())

    sender = threading.Thread(target=send, daemon=True)
    got, gaps = 0, 0
    t0 = t_last = time.perf_counter()
    try:
        sender.start()
        while got < len(frames):
            try:
                reading = await sensor.read()
            except DeviceError:
                break  # nothing for stale_after_s: the rest was lost
            got, gaps = got + 1, gaps + reading.frames_lost
            t_last = time.perf_counter()
        sender.join()
        return CanRun(
            offered=len(frames), decoded=got, gap_frames=gaps, send_s=sent_at[0] - t0, decode_s=t_last - t0
        )
    finally:
        await sensor.close()
        tx.shutdown()
        rx.shutdown()


def _raw_rate(frames: list[can.Message]) -> float:
    channel = f"raw-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    rx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    try:
        t0 = time.perf_counter()
        for m in frames:
            tx.send(m)
        got = 0
        while got < len(frames) and (msg := rx.recv(timeout=1.0)) is not None:
            decode_frame(msg.arbitration_id, bytes(msg.data))
            got += 1
        return got / (time.perf_counter() - t0)
    finally:
        tx.shutdown()
        rx.shutdown()


def bench_can(*, burst: int, rates: list[float], seconds: float, repeats: int) -> dict[str, float]:
    """Decoded rate at the highest paced rate the driver sustains (``CanRun.sustained``), the driver's burst
    decode rate and loss, and a bare decode loop over the same burst as the peer."""
    sustained_rate, offered, failed_at, lost = 0.0, 0.0, 0.0, 0
    for rate in rates:
        batch = _frames(int(rate * seconds))
        runs = [asyncio.run(_driver_run(batch, rate)) for _ in range(repeats)]
        if sum(r.sustained(rate) for r in runs) * 2 <= len(runs):  # not sustained in most runs
            failed_at = rate
            break
        lost = max(lost, *(r.offered - r.decoded + r.gap_frames for r in runs))
        sustained_rate, offered = statistics.median(r.rate_per_s for r in runs), rate
    bursts = [asyncio.run(_driver_run(_frames(burst), None)) for _ in range(repeats)]
    raw = statistics.median(_raw_rate(_frames(burst)) for _ in range(repeats))
    burst_rate = statistics.median(r.rate_per_s for r in bursts)
    return {
        "can_frames_per_s": sustained_rate,
        "can_frames_lost": float(lost),
        "can_offered_rate_per_s": offered,
        "can_first_unsustained_rate_per_s": failed_at,
        "can_burst_frames_per_s": burst_rate,
        "can_burst_lost": float(max(r.offered - r.decoded + r.gap_frames for r in bursts)),
        "raw_can_frames_per_s": raw,
        "can_driver_vs_raw": burst_rate / raw,
    }


# ------------------------------------------------------------------------------------------ ring buffer
def bench_ring(*, appends: int) -> dict[str, float]:
    """µs per append; ms per 60-min window copy at 1 Hz from a 2-hour buffer."""
    ring = RingBuffer(2 * 3600)
    quality = np.zeros(32, dtype=np.uint8)
    t0 = datetime(2026, 1, 1, tzinfo=UTC).timestamp()
    samples = [
        Sample(
            t=datetime.fromtimestamp(t0 + i, UTC),
            temps_c=np.full(32, 20.0 + i * 1e-3),
            ambient_c=21.0,
            speed_rpm=3000.0,
            torque_nm=5.0,
            quality=quality,
        )
        for i in range(appends)
    ]
    t = time.perf_counter()
    for s in samples:
        ring.append(s)
    append_us = (time.perf_counter() - t) / appends * 1e6
    t_end = t0 + appends - 1
    window_ms = []
    for _ in range(30):
        t = time.perf_counter()
        w = ring.window(t_end - 3599, t_end)
        window_ms.append((time.perf_counter() - t) * 1e3)
    assert len(w) == 3600
    return {"ring_append_us": append_us, "ring_window_ms": statistics.median(window_ms)}


# ------------------------------------------------------------------------------------ reconnect and CPU
async def _reconnect(dev: Devices, outage_s: float, repeats: int) -> list[float]:
    """Seconds from the DAQ's return after each of ``repeats`` outages to the first good reading."""
    daq = ModbusDaq("127.0.0.1", dev.port, timeout_s=0.5)
    good: list[float] = []
    task = asyncio.create_task(daq.run(interval_s=0.1, on_reading=lambda r: good.append(time.monotonic())))
    out = []
    try:
        for _ in range(repeats):
            while not good:
                await asyncio.sleep(0.05)
            await asyncio.to_thread(dev.command, "inject", FaultKind.DROP.value)
            await asyncio.sleep(outage_s)
            good.clear()
            await asyncio.to_thread(dev.command, "clear", FaultKind.DROP.value)
            back = time.monotonic()
            while not good or good[-1] < back:
                await asyncio.sleep(0.01)
            out.append(min(t for t in good if t >= back) - back)
        return out
    finally:
        task.cancel()
        await daq.close()


async def _cpu(
    dev: Devices, seconds: float, *, modbus: bool = True, can_bus: bool = True, batch_s: float | None = None
) -> float:
    """CPU % of one core used by this process while acquiring (DAQ at 10 Hz and/or CAN at 100 Hz).

    ``batch_s``: the CAN driver's wake-up batching (None: its default)."""
    daq = ModbusDaq("127.0.0.1", dev.port, timeout_s=1.0)
    batch = BATCH_S if batch_s is None else batch_s
    sensor = CanSpindleSensor(interface="remote", channel=dev.hub_url, stale_after_s=1.0, batch_s=batch)
    tasks = []
    if modbus and can_bus:
        acq = Acquisition(daq, sensor, RingBuffer(3600), period_s=1.0)
        tasks.append(asyncio.create_task(acq.run(poll_interval_s=0.1)))
    elif modbus:
        tasks.append(asyncio.create_task(daq.run(interval_s=0.1)))
    else:
        tasks.append(asyncio.create_task(sensor.run(interval_s=0.0)))
    try:
        await asyncio.sleep(2.0)  # connect and settle
        frames0, reads0 = sensor.metrics.events.get("frames", 0), daq.metrics.reads_ok
        c0, w0 = time.process_time(), time.monotonic()
        await asyncio.sleep(seconds)
        c1, w1 = time.process_time(), time.monotonic()
        if (can_bus and sensor.metrics.events.get("frames", 0) == frames0) or (
            modbus and daq.metrics.reads_ok == reads0
        ):
            raise RuntimeError("acquisition did not receive data during the CPU measurement")
        return (c1 - c0) / (w1 - w0) * 100.0
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await daq.close()
        await sensor.close()


class _PacedSender(threading.Thread):
    """Sends ``SpindleStatus`` every 10 ms on ``bus``; ``cpu_s`` is its own CPU time (``thread_time``)."""

    def __init__(self, bus: can.BusABC) -> None:
        super().__init__(daemon=True)
        self.bus, self.cpu_s, self.stop = bus, 0.0, threading.Event()

    def run(self) -> None:
        t0, k = time.perf_counter(), 0
        while not self.stop.is_set():
            data = encode_status(3000, 5.0, k % 16, 0)
            self.bus.send(can.Message(arbitration_id=SPINDLE_STATUS_ID, is_extended_id=False, data=data))
            k += 1
            self.cpu_s = time.thread_time()
            self.stop.wait(max(0.0, t0 + 0.01 * k - time.perf_counter()))


async def _cpu_local_can(dev: Devices, seconds: float) -> float:
    """Like ``_cpu`` but CAN arrives on an in-process ``virtual`` bus from a sender thread whose own CPU time
    is subtracted: close to a kernel CAN interface (socketcan), where the sender is not this process."""
    channel = f"cpu-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    rx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    sender = _PacedSender(tx)
    daq = ModbusDaq("127.0.0.1", dev.port, timeout_s=1.0)
    sensor = CanSpindleSensor(bus=rx, stale_after_s=1.0)
    task = asyncio.create_task(
        Acquisition(daq, sensor, RingBuffer(3600), period_s=1.0).run(poll_interval_s=0.1)
    )
    sender.start()
    try:
        await asyncio.sleep(2.0)
        c0, s0, w0 = time.process_time(), sender.cpu_s, time.monotonic()
        await asyncio.sleep(seconds)
        c1, s1, w1 = time.process_time(), sender.cpu_s, time.monotonic()
        return ((c1 - c0) - (s1 - s0)) / (w1 - w0) * 100.0
    finally:
        sender.stop.set()
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await daq.close()
        await sensor.close()
        sender.join(1.0)
        tx.shutdown()
        rx.shutdown()


# ------------------------------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks acquisition``."""
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--repeats", type=int, default=3, help="runs per repeated figure (default 3)")
    parser.add_argument("--polls", type=int, default=300, help="Modbus polls per run (default 300)")
    parser.add_argument(
        "--can-burst", type=int, default=20_000, help="CAN burst size, frames (default 20000)"
    )
    parser.add_argument(
        "--can-rates",
        default="2500,5000,10000,15000,20000",
        help="CAN send rates to try, frames/s (comma-separated)",
    )
    parser.add_argument(
        "--can-seconds", type=float, default=3.0, help="CAN send time per rate, s (default 3)"
    )
    parser.add_argument(
        "--outage-s", type=float, default=10.0, help="DAQ outage before reconnect (default 10)"
    )
    parser.add_argument("--cpu-s", type=float, default=5.0, help="CPU measurement length, s (default 5)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Measure every figure; returns them with units in the key names."""
    results: dict[str, Any] = {"measured_at_utc": datetime.now(UTC).isoformat()}
    results["load_avg_1min_before"] = os.getloadavg()[0]
    results |= bench_ring(appends=2 * 3600)
    rates = [float(r) for r in args.can_rates.split(",") if r.strip()]
    results |= bench_can(burst=args.can_burst, rates=rates, seconds=args.can_seconds, repeats=args.repeats)
    with devices() as dev:
        results |= bench_modbus(dev, polls=args.polls, repeats=args.repeats)
        reconnects = asyncio.run(_reconnect(dev, args.outage_s, args.repeats))
        results["reconnect_s"] = statistics.median(reconnects)
        results["reconnect_s_max"] = max(reconnects)
        results["outage_s"] = args.outage_s
        results["cpu_pct_10hz"] = asyncio.run(_cpu(dev, args.cpu_s))
        results["cpu_pct_modbus_only"] = asyncio.run(_cpu(dev, args.cpu_s, can_bus=False))
        results["cpu_pct_can_only"] = asyncio.run(_cpu(dev, args.cpu_s, modbus=False))
        results["cpu_pct_10hz_local_can"] = asyncio.run(_cpu_local_can(dev, args.cpu_s))
        results["cpu_pct_10hz_can_batch_50ms"] = asyncio.run(_cpu(dev, args.cpu_s, batch_s=0.05))
    results["targets_met"] = {k: _meets(results[k], op, v) for k, (op, v) in TARGETS.items()}
    # the decoded rate includes the pipeline's tail, so the target is judged on the sustained offered rate
    can_ok = (
        results["can_offered_rate_per_s"] >= TARGETS["can_frames_per_s"][1] and not results["can_frames_lost"]
    )
    results["targets_met"]["can_frames_per_s"] = can_ok
    return results


def _meets(value: float, op: str, target: float) -> bool:
    return {"<=": value <= target, ">=": value >= target, "<": value < target}[op]


def main(args: argparse.Namespace) -> int:
    """Print the figures (a table, or JSON with ``--json``)."""
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # the outage makes pymodbus dump frames
    results = run(args)
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print(f"acquisition benchmark, {results['measured_at_utc']}")
    for key, value in results.items():
        if isinstance(value, float):
            target = TARGETS.get(key)
            note = ""
            if target:
                verdict = "ok" if results["targets_met"][key] else "MISSED"
                note = f"   target {target[0]} {target[1]:g}: {verdict}"
            print(f"  {key:<36} {value:12.4g}{note}")
    return 0
