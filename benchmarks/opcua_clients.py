"""The OPC UA clients of ``python -m benchmarks opcua --spindles N``: the readers (a subprocess of their own,
so their CPU is not the REST load's) and the browse-and-compare check against REST (in the bench's process).

Readers: ``clients`` asyncua clients, each reading the 10 compensation nodes of one spindle in one Read (as a
PLC's ``OPC_UA_ReadList``) ``read_rate`` times a second, open loop; client k's i-th read goes to spindle
``spread(i, k, n)``. The subprocess prints ``{"connected": k}`` once every client has its session, then one
JSON result ``{"latencies_s", "errors", "bad", "per_spindle"}``: ``errors`` the reads that failed (an
exception or a timeout), ``bad`` per node path how many of its values came back with a Bad StatusCode
(the verdict's, e.g. Bad_WaitingForInitialData before a spindle's first growth: not a failure of the read).
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections.abc import Sequence
from typing import Any

from benchmarks.opcua_figures import (
    COMPARED,
    COMPENSATION_NODES,
    STATUS_NODES,
    UaValue,
    differences,
    spread,
)

__all__ = ["NS", "READ_NODES", "equal_to_rest", "readers"]

NS = "urn:spindle-chtc:opcua"
READ_NODES = COMPENSATION_NODES  # each client reads one spindle's in one Read
GROUPS = {"Status", "H", "Condition", "Temperatures", "Growth", "Controller", "Devices"}


def readers(config: str) -> None:
    """Entry point of the readers' subprocess: ``config`` is JSON {endpoint, spindles, clients, read_rate,
    duration_s}."""
    cfg = json.loads(config)
    print(json.dumps(asyncio.run(_readers(cfg))), flush=True)


async def _readers(cfg: dict[str, Any]) -> dict[str, Any]:
    from asyncua import Client, ua

    ids: list[str] = cfg["spindles"]
    clients = [Client(cfg["endpoint"], timeout=10) for _ in range(cfg["clients"])]
    for c in clients:
        await c.connect()
    idx = await clients[0].get_namespace_index(NS)
    print(json.dumps({"connected": len(clients)}), flush=True)
    loop = asyncio.get_running_loop()
    lat: list[float] = []
    errors = 0
    bad: dict[str, int] = {}
    per_spindle = dict.fromkeys(ids, 0)
    rate, duration = float(cfg["read_rate"]), float(cfg["duration_s"])
    t0 = loop.time() + 0.2

    async def reader(k: int, c: Client) -> None:
        nonlocal errors
        nodes = {sid: [c.get_node(f"ns={idx};s={sid}.{p}") for p in READ_NODES] for sid in ids}
        for i in range(int(rate * duration)):
            due = t0 + (i + k / len(clients)) / rate
            if (delay := due - loop.time()) > 0:
                await asyncio.sleep(delay)
            sid = ids[spread(i, k, len(ids))]
            start = time.perf_counter()
            try:
                values = await c.read_attributes(nodes[sid], ua.AttributeIds.Value)
                for path, v in zip(READ_NODES, values, strict=True):
                    if v.StatusCode_.value >> 30 == 2:
                        bad[path] = bad.get(path, 0) + 1
            except Exception:
                errors += 1
            lat.append(time.perf_counter() - start)
            per_spindle[sid] += 1

    await asyncio.gather(*(reader(k, c) for k, c in enumerate(clients)))
    for c in clients:
        await c.disconnect()
    return {"latencies_s": lat, "errors": errors, "bad": bad, "per_spindle": per_spindle}


# --- every spindle browsable, and equal to REST at the same `at` ------------------------------------------
async def equal_to_rest(
    endpoint: str, rest_url: str, spindles: Sequence[str], *, tries: int = 20
) -> dict[str, Any]:
    """For each spindle: its object is of ``SpindleThermalModelType`` with the documented groups, and its
    values and StatusCodes equal its ``/compensation`` at the same ``at`` (REST read before and after the
    OPC UA read, both at that ``at``; retried on a new sample, up to ``tries`` times). Returns
    {"equal": bool, "spindles": {id: [differences]}, "tries": {id: n}}."""
    import httpx
    from asyncua import Client

    diffs: dict[str, list[str]] = {}
    used: dict[str, int] = {}
    async with Client(endpoint, timeout=10) as c, httpx.AsyncClient(timeout=10.0) as http:
        idx = await c.get_namespace_index(NS)
        for sid in spindles:
            diffs[sid] = await _browse(c, idx, sid)
            url = f"{rest_url}/api/v1/spindles/{sid}/compensation"
            for n in range(1, tries + 1):
                before = (await http.get(url)).json()
                got = await _read(c, idx, sid)
                after = (await http.get(url)).json()
                used[sid] = n
                same = before.get("at") is not None and before.get("at") == after.get("at")
                if same and not differences(before, got):
                    break
                await asyncio.sleep(0.3)
            else:
                diffs[sid] += [f"after {tries} tries: "] + (
                    differences(before, got) if same else ["no same at"]
                )
    return {"equal": not any(diffs.values()), "spindles": diffs, "tries": used}


async def _browse(c: Any, idx: int, sid: str) -> list[str]:
    node = c.get_node(f"ns={idx};s={sid}")
    typedef = (await node.read_type_definition()).Identifier
    groups = {(await n.read_browse_name()).Name for n in await node.get_children()}
    out = [] if typedef == "SpindleThermalModelType" else [f"type {typedef}"]
    return out + ([f"groups missing: {sorted(GROUPS - groups)}"] if not groups >= GROUPS else [])


async def _read(c: Any, idx: int, sid: str) -> dict[str, UaValue]:
    from asyncua import ua

    paths = (*STATUS_NODES, *COMPARED)
    nodes = [c.get_node(f"ns={idx};s={sid}.{p}") for p in paths]
    values = await c.read_attributes(nodes, ua.AttributeIds.Value)
    return {
        p: UaValue(dv.Value.Value if dv.Value is not None else None, dv.StatusCode_.value, dv.SourceTimestamp)
        for p, dv in zip(paths, values, strict=True)
    }


if __name__ == "__main__":  # pragma: no cover
    readers(sys.argv[1])
