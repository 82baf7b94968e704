"""Helpers for the driver tests: free ports, polling with a deadline, loopback Modbus servers, fake clocks."""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import Callable
from dataclasses import dataclass, field

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def poll_until(predicate: Callable[[], bool], *, timeout_s: float = 5.0, every_s: float = 0.01) -> None:
    """Wait until ``predicate()`` is true; fail the test after ``timeout_s``."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not predicate():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s")
        await asyncio.sleep(every_s)


@dataclass
class FakeClock:
    """Monotonic clock under test control (seconds)."""

    t: float = 1000.0

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


@dataclass
class PymodbusDaqServer:
    """A real pymodbus TCP server serving ``words`` (address → word) as input registers on ``blocks``.

    Addresses outside ``blocks`` draw exception 2 (illegal data address). While ``hang`` is set, requests
    are held (the device stops answering) until it is cleared.
    """

    port: int
    words: dict[int, int]
    blocks: list[tuple[int, int]] = field(default_factory=lambda: [(0, 33), (100, 33), (200, 2)])
    unit: int = 1
    hang: asyncio.Event = field(default_factory=asyncio.Event)
    function_codes: list[int] = field(default_factory=list)
    _server: ModbusTcpServer | None = None

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: object,
    ) -> None:
        self.function_codes.append(function_code)
        while self.hang.is_set():
            await asyncio.sleep(0.01)
        for i in range(len(current_registers)):
            current_registers[i] = self.words.get(start_address + i, 0)

    async def start(self) -> PymodbusDaqServer:
        simdata = [SimData(a, count=c, datatype=DataType.REGISTERS) for a, c in self.blocks]
        device = SimDevice(id=self.unit, simdata=simdata, action=self._action)
        self._server = ModbusTcpServer(device, address=("127.0.0.1", self.port))
        await self._server.serve_forever(background=True)
        return self

    async def stop(self) -> None:
        if self._server is not None:
            await self._server.shutdown()
            self._server = None


@dataclass
class RawModbusServer:
    """A tiny hand-written Modbus TCP server that answers FC4 requests in a chosen (broken) way.

    ``mode``: "short" (valid frame, ``short_by`` registers fewer), "truncated" (MBAP announces the full
    reply, only part is sent), "garbage" (bytes that are no Modbus frame), "ok" (correct reply, zeros).
    """

    port: int
    mode: str = "ok"
    short_by: int = 1
    _server: asyncio.AbstractServer | None = None

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                req = await reader.readexactly(12)
                tid, _proto, _len, unit, fc, _addr, count = struct.unpack(">HHHBBHH", req)
                writer.write(self._reply(tid, unit, fc, count))
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError, asyncio.CancelledError):
            pass
        finally:
            writer.close()

    def _reply(self, tid: int, unit: int, fc: int, count: int) -> bytes:
        n = count - self.short_by if self.mode == "short" else count
        pdu = struct.pack(">BB", fc, 2 * n) + b"\x00\x01" * n
        frame = struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu
        if self.mode == "truncated":
            return frame[: 7 + 2 + 2 * (n // 2)]
        if self.mode == "garbage":
            return b"\xde\xad\xbe\xef garbage \xff\xff"
        return frame

    async def start(self) -> RawModbusServer:
        self._server = await asyncio.start_server(self._handle, "127.0.0.1", self.port)
        return self

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
