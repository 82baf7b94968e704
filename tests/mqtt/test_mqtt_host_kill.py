"""``kill -9`` of a host (issue 43, "Hosted outlets": ``kill -9`` -> NDEATH): ``chtc run`` with two
``[[spindles]]`` and ``[mqtt] enabled`` as a subprocess, against two ``chtc simulate`` subprocesses (Modbus
TCP on a free loopback port, CAN through a python-can-remote hub) and the test's own Mosquitto
(``tests.mqtt.peers.broker``). After the NBIRTH and both DBIRTHs (and DDATA from both devices), SIGKILL to the
host's process group: the broker delivers the edge node's Will, exactly one NDEATH, with the bdSeq of its
NBIRTH, and no DDATA follow it. Messages are decoded with the repo's ``sparkplug_b_pb2``."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import aiomqtt
import pytest

from service.serve.mqtt import sparkplug_b_pb2 as pb
from tests.mqtt.peers import MOSQUITTO, Broker, broker, free_port, wait_port
from tests.mqtt.test_mqtt_hosted import _decode, until

ROOT = Path(__file__).resolve().parents[2]
NODE = "host-1"
SPINDLES = ("a", "b")


@dataclass
class Heard:
    """Every message of one Sparkplug group: (monotonic time, topic, decoded payload)."""

    msgs: list[tuple[float, str, pb.Payload]] = field(default_factory=list)

    def of(self, kind: str, *, node: str = NODE) -> list[tuple[float, str, pb.Payload]]:
        return [m for m in self.msgs if m[1].split("/")[2:4] == [kind, node]]

    def devices(self, kind: str) -> set[str]:
        return {t.split("/")[4] for _, t, _ in self.of(kind)}


@contextlib.asynccontextmanager
async def listen(port: int, group: str) -> AsyncIterator[Heard]:
    heard = Heard()
    async with aiomqtt.Client("127.0.0.1", port, identifier=f"test-kill-{os.getpid()}") as client:
        await client.subscribe(f"spBv1.0/{group}/#", qos=1)

        async def collect() -> None:
            async for m in client.messages:
                assert isinstance(m.payload, bytes)
                heard.msgs.append((time.monotonic(), str(m.topic), _decode(m.payload)))

        task = asyncio.create_task(collect())
        try:
            yield heard
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)


def bdseq(p: pb.Payload) -> int:
    return int(next(m.long_value for m in p.metrics if m.name == "bdSeq"))


def chtc(*argv: str, log: Path, env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "service.cli", *argv],
            env=(env or dict(os.environ)) | {"PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"},
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=log.parent,
        )


@contextlib.contextmanager
def killed_at_exit(procs: list[subprocess.Popen[bytes]]) -> Iterator[list[subprocess.Popen[bytes]]]:
    try:
        yield procs
    finally:
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


def host_config(tmp: Path, mqtt_port: int, group: str, rigs: dict[str, tuple[int, int]]) -> Path:
    spindles = "".join(
        f'[[spindles]]\nid = "{sid}"\nmodbus = {{ port = {daq} }}\n'
        f'can = {{ channel = "ws://127.0.0.1:{hub}/" }}\n'
        for sid, (daq, hub) in rigs.items()
    )
    path = tmp / "host.toml"
    path.write_text(
        f'[api]\nhost = "127.0.0.1"\nport = {free_port()}\n'
        f'[database]\nurl = "sqlite:///{tmp / "fleet.db"}"\n'
        "[engine]\nidentification_workers = 1\n"
        '[can]\ninterface = "remote"\n'
        f'[mqtt]\nenabled = true\nhost = "127.0.0.1"\nport = {mqtt_port}\ngroup_id = "{group}"\n'
        f'edge_node_id = "{NODE}"\nstate_dir = "{tmp / "state"}"\ntick_s = 1.0\n'
        f"{spindles}",
        encoding="utf-8",
    )
    return path


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[Broker]:
    if not Path(MOSQUITTO).exists():
        pytest.skip("mosquitto not installed (.ci/run installs it)")
    with broker(tmp_path) as b:
        yield b


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_kill_9_of_a_host_gives_one_ndeath_with_the_nbirth_bdseq_and_no_ddata_after(
    mosquitto: Broker, tmp_path: Path
) -> None:
    group = f"kill{os.getpid()}"
    rigs = {sid: (free_port(), free_port()) for sid in SPINDLES}
    logs = {sid: tmp_path / f"sim-{sid}.log" for sid in SPINDLES} | {"host": tmp_path / "host.log"}

    async def scenario(procs: list[subprocess.Popen[bytes]]) -> None:
        for sid, (daq, hub) in rigs.items():
            procs.append(
                chtc(
                    "simulate",
                    *("--profile", "steps", "--loop", "--speedup", "40", "--modbus-port", str(daq)),
                    *("--can-channel", f"ws://127.0.0.1:{hub}/"),
                    log=logs[sid],
                )
            )
        for daq, _ in rigs.values():
            await asyncio.to_thread(wait_port, daq, up=True, timeout_s=120.0)
        async with listen(mosquitto.port, group) as heard:
            config = host_config(tmp_path, mosquitto.port, group, rigs)
            host = chtc("run", "--config", str(config), log=logs["host"])
            procs.append(host)
            t0 = time.monotonic()
            born = await until(lambda: heard.devices("DBIRTH") == set(SPINDLES), 180.0, every_s=0.2)
            assert born, f"births: {heard.devices('DBIRTH')}, host exit {host.poll()}"
            assert await until(lambda: heard.devices("DDATA") == set(SPINDLES), 60.0), heard.devices("DDATA")
            births = heard.of("NBIRTH")
            assert len(births) == 1, [t for _, t, _ in heard.msgs]
            assert not heard.of("NDEATH")
            first = bdseq(births[0][2])
            print(f"births and DDATA of both after {time.monotonic() - t0:.1f} s; NBIRTH bdSeq {first}")

            t_kill = time.monotonic()
            os.killpg(host.pid, signal.SIGKILL)
            await asyncio.to_thread(host.wait, 10)
            assert host.returncode == -signal.SIGKILL
            assert await until(lambda: bool(heard.of("NDEATH")), 15.0), "no NDEATH after kill -9"
            t_death = heard.of("NDEATH")[0][0]
            print(f"NDEATH {t_death - t_kill:.2f} s after the SIGKILL")
            await asyncio.sleep(3.0)  # anything still to come would arrive here (tick_s 1 s)
            deaths = heard.of("NDEATH")
            assert len(deaths) == 1, [t for _, t, _ in deaths]
            nd = deaths[0][2]
            assert bdseq(nd) == first and not nd.HasField("seq")
            late = [t for when, t, _ in heard.msgs if when >= t_death and "/DDATA/" in t]
            assert not late, late

    with killed_at_exit([]) as procs:
        try:
            asyncio.run(scenario(procs))
        except AssertionError:
            for log in logs.values():
                print(f"--- {log.name}\n{log.read_text(errors='replace')[-3000:]}")
            raise
