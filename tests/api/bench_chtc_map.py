"""Cost of GET /api/v1/chtc/map on the real service in speed-map mode (docs/design/api.md, "H map").

``python3 -m tests.api.bench_chtc_map``: the service of the API tests (``served_map_mode``: 26.7 min of a
seeded duty cycle, several map fits), then medians and 99th percentiles of ``chtc_map()``, of building
and serialising the body, and of ``TestClient`` GETs of ``/chtc/map`` (200 from the cached body, 304) and
``/chtc``; the body's size and an abridged body.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from fastapi.testclient import TestClient

from api.app import create_app
from api.schemas import chtc_map_out
from service.settings import Settings
from tests.api.conftest import served_map_mode


def _ms(f: Callable[[], object], n: int = 200) -> str:
    out = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        out.append(time.perf_counter() - t)
    out.sort()
    return f"median {statistics.median(out) * 1e3:.3f} ms, p99 {out[int(0.99 * n) - 1] * 1e3:.3f} ms"


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp, served_map_mode(Path(tmp)) as s:
        svc = s.service
        with TestClient(create_app(Settings(), svc, clock=s.clock)) as c:
            r = c.get("/api/v1/chtc/map")
            etag = r.headers["etag"]
            snap = svc.chtc_map()
            assert snap is not None
            print(f"body {len(r.content)} bytes, status {r.json()['status']}")
            print("chtc_map():", _ms(svc.chtc_map, 2000))
            sid = r.json()["spindle_id"]
            print(
                "body build + JSON:",
                _ms(lambda: chtc_map_out(snap, s.clock.now, spindle_id=sid).model_dump_json()),
            )
            print("GET /chtc/map 200:", _ms(lambda: c.get("/api/v1/chtc/map")))
            print(
                "GET /chtc/map 304:", _ms(lambda: c.get("/api/v1/chtc/map", headers={"If-None-Match": etag}))
            )
            print("GET /chtc:", _ms(lambda: c.get("/api/v1/chtc")))
            body = r.json()
            for key in ("speeds_rpm",):
                body[key] = [*body[key][:3], "...", *body[key][-1:]]
            body["zones"] = [
                {k: ([*v[:2], "..."] if isinstance(v, list) else v) for k, v in z.items()}
                for z in body["zones"][:1]
            ] + ["..."]
            body["visited"] = [*body["visited"][:2], "..."]
            print(json.dumps(body, ensure_ascii=False))


if __name__ == "__main__":
    main()
