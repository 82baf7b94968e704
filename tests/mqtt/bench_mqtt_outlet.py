"""Cost of the MQTT outlet's work per view on the real service (docs/integration.md, "MQTT").

``python3 -m tests.mqtt.bench_mqtt_outlet``: the service of the API tests (``served_service``, a seeded plan
fed in full), then medians and 99th percentiles of reading every metric from a fresh ``ViewReader``
(``read_points``: in a thread, off the event loop) and of encoding a DBIRTH and a DDATA with every metric (on
the loop), with the payload sizes.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable

from service.serve.mqtt.points import read_points
from service.serve.mqtt.sparkplug import SparkplugSession, SparkplugTopics
from simulator.served import served_service


def _ms(f: Callable[[], object], n: int = 200) -> str:
    out = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        out.append(time.perf_counter() - t)
    out.sort()
    return f"median {1e3 * statistics.median(out):.3f} ms, p99 {1e3 * out[int(0.99 * n) - 1]:.3f} ms"


def main() -> None:
    with tempfile.TemporaryDirectory() as d, served_service(database_url=f"sqlite:///{d}/chtc.db") as served:
        svc = served.service
        now = served.clock()
        points = read_points(svc.reader(), now=now, heartbeat=0)  # the growth terms, once
        read = _ms(lambda: read_points(svc.reader(), now=now, heartbeat=1))
        print(f"read_points (a fresh reader each): {read}")
        s = SparkplugSession(SparkplugTopics("chtc", "chtc-1", "spindle1"))
        (_, nb), (_, db) = s.births(0, points, now)
        births = _ms(lambda: s.births(0, points, now))
        print(f"NBIRTH {len(nb)} B, DBIRTH {len(db)} B ({len(points)} metrics): {births}")
        body = s.data(points, now)
        print(f"DDATA with every metric {len(body)} B: {_ms(lambda: s.data(points, now))}")
        print({k: points[k].value for k in ("Status/Code", "Status/Usable", "Status/Reason", "Growth/Axial")})


if __name__ == "__main__":
    main()
