"""The load of the API benches (``python -m benchmarks api``, ``opcua``): an open-loop GET load through a raw
HTTP/1.1 client or httpx, and the API's own latency histogram between two scrapes (shared by
``benchmarks.api``, ``benchmarks.api_live`` and ``benchmarks.opcua``, so none of them imports another)."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Sequence
from typing import Any

import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

__all__ = ["HttpxClient", "RawClient", "_load", "_server_buckets", "histogram_quantile"]


# --- load ---------------------------------------------------------------------------------------------
class RawClient:
    """A minimal HTTP/1.1 keep-alive GET client on asyncio streams: measures the server, not httpx."""

    def __init__(self, url: str, headers: str = "") -> None:
        rest = url.removeprefix("http://")
        hostport, _, path = rest.partition("/")
        self.host, port = hostport.split(":")
        self.port = int(port)
        self.request = f"GET /{path} HTTP/1.1\r\nHost: {hostport}\r\n{headers}\r\n".encode()
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def get(self) -> int:
        if self.reader is None or self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        self.writer.write(self.request)
        head = await self.reader.readuntil(b"\r\n\r\n")
        length = 0
        for line in head.split(b"\r\n"):
            if line.lower().startswith(b"content-length:"):
                length = int(line.split(b":", 1)[1])
        await self.reader.readexactly(length)
        return int(head.split(b" ", 2)[1])

    async def aclose(self) -> None:
        if self.writer is not None:
            self.writer.close()


class HttpxClient:
    def __init__(self, url: str) -> None:
        self.url = url
        self.client = httpx.AsyncClient(limits=httpx.Limits(max_connections=1), timeout=5.0)

    async def get(self) -> int:
        return (await self.client.get(self.url)).status_code

    async def aclose(self) -> None:
        await self.client.aclose()


async def _load(
    url: str,
    *,
    rate: float,
    duration_s: float,
    clients: int,
    kind: str,
    headers: str = "",
    records: list[tuple[float, float]] | None = None,
    rotate: Sequence[str] = (),
) -> dict[str, Any]:
    """Open-loop load; ``records`` (if given) gets (send time perf_counter, latency s) per request;
    ``rotate`` (raw clients only): request i goes to ``rotate[i % len(rotate)]`` instead of ``url``."""
    if rotate and kind != "raw":
        raise ValueError("_load: rotate needs kind='raw'")
    targets = [RawClient(u, headers).request for u in rotate]
    n = max(1, int(rate * duration_s))
    loop = asyncio.get_running_loop()
    lat: list[float] = []
    late: list[float] = []
    errors = 0
    statuses: dict[int, int] = {}
    pool: list[Any] = [RawClient(url, headers) if kind == "raw" else HttpxClient(url) for _ in range(clients)]
    for c in pool:  # open the connections before the clock starts
        await c.get()
    t0 = loop.time() + 0.1

    async def worker(w: int, client: Any) -> None:
        nonlocal errors
        for i in range(w, n, clients):
            due = t0 + i / rate
            if (delay := due - loop.time()) > 0:
                await asyncio.sleep(delay)
            late.append(max(0.0, loop.time() - due))
            if targets:
                client.request = targets[i % len(targets)]
            start = time.perf_counter()
            status = await client.get()
            lat.append(time.perf_counter() - start)
            if records is not None:
                records.append((start, lat[-1]))
            errors += status != 200
            statuses[status] = statuses.get(status, 0) + 1

    try:
        await asyncio.gather(*(worker(w, c) for w, c in enumerate(pool)))
    finally:
        for c in pool:
            await c.aclose()
    ms = np.array(lat) * 1e3
    return {
        "requests": len(lat),
        "errors": errors,
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
        "late_ms_p99": float(np.percentile(np.array(late) * 1e3, 99)),
        "achieved_rps": len(lat) / (max(late) + n / rate) if late else 0.0,
        "statuses": statuses,
    }


def _server_buckets(url: str) -> dict[float, float]:
    """The API's own cumulative latency buckets (s -> count) for 200s of GET /api/v1/chtc."""
    text = httpx.get(url + "/api/v1/metrics", timeout=10.0).text
    out: dict[float, float] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples if fam.name == "chtc_http_request_duration_seconds" else ():
            if (
                s.name.endswith("_bucket")
                and s.labels.get("route") == "/api/v1/chtc"
                and s.labels["status"] == "200"
            ):
                out[float(s.labels["le"])] = s.value
    return out


def histogram_quantile(q: float, before: dict[float, float], after: dict[float, float]) -> float | None:
    """Prometheus-style quantile (linear within the bucket) of the observations between two scrapes, s."""
    les = sorted(after)
    counts = [after[le] - before.get(le, 0.0) for le in les]
    if not counts or counts[-1] <= 0:
        return None
    rank, prev_le, prev_c = q * counts[-1], 0.0, 0.0
    for le, c in zip(les, counts, strict=True):
        if c >= rank:
            return (
                prev_le
                if math.isinf(le)
                else prev_le + (le - prev_le) * (rank - prev_c) / max(c - prev_c, 1e-12)
            )
        prev_le, prev_c = le, c
    return prev_le
