"""GET /temperature-field under load (issue 13.4): the locator is built once per mesh, bodies are cached
per field with an ETag and gzip, equal to the pydantic serialisation, and excess requests are shed."""

from __future__ import annotations

import gzip
import json
import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from api.app import create_app
from api.routers.field import grid_out, mesh_out
from api.routers.field_render import FieldRenderer
from service.engine.shell import SoftSensorService
from service.estimate.locator import TriangleLocator, locator_for
from service.serve.interface import FieldSnapshot
from service.settings import Settings
from service.sim.served import Served

URL = "/api/v1/temperature-field"


def test_locator_is_shared_by_every_snapshot_of_a_mesh(ro_service: SoftSensorService) -> None:
    """The running service builds a new snapshot for every at=now request: its locator must not be rebuilt."""
    f = ro_service.field("now")
    again = FieldSnapshot(f.t, "now", f.nodes_rz, f.triangles, f.temps_c + 1.0, f.identification_id)
    assert again.locator is f.locator
    other_mesh = FieldSnapshot(f.t, "now", f.nodes_rz.copy(), f.triangles, f.temps_c)
    assert other_mesh.locator is not f.locator
    assert locator_for(f.nodes_rz, f.triangles) is f.locator


def test_cached_grid_locations_equal_fresh_ones(ro_service: SoftSensorService) -> None:
    f = ro_service.field("now")
    r, z, located = f.locator.grid(12, 30)
    rr, zz = np.meshgrid(r, z, indexing="ij")
    fresh = TriangleLocator(f.nodes_rz, f.triangles).locate(np.c_[rr.ravel(), zz.ravel()])
    np.testing.assert_array_equal(located.tri, fresh.tri)
    assert f.locator.grid(12, 30)[2] is located


@pytest.mark.parametrize("fmt", ["mesh", "grid"])
def test_fast_bodies_equal_the_schema_serialisation(ro_service: SoftSensorService, fmt: str) -> None:
    f = ro_service.field("steady")
    renderer = FieldRenderer()
    if fmt == "mesh":
        fast, reference = renderer.mesh(f), mesh_out(f)
    else:
        fast, reference = renderer.grid(f, 12, 30), grid_out(f, 12, 30)
    assert json.loads(fast.body) == json.loads(reference.model_dump_json())
    assert gzip.decompress(fast.gzip()) == fast.body


def test_a_new_field_reuses_the_geometry_and_makes_a_new_body(ro_service: SoftSensorService) -> None:
    f = ro_service.field("now")
    renderer = FieldRenderer()
    a = renderer.mesh(f)
    assert renderer.mesh(replace(f)) is a  # same content: cached
    g = replace(f, temps_c=f.temps_c + 0.5)
    b = renderer.mesh(g)
    assert b.etag != a.etag and renderer.builds == 2
    assert json.loads(b.body) == json.loads(mesh_out(g).model_dump_json())
    assert gzip.decompress(b.gzip()) == b.body  # the primed compressor, copied per field


def test_mesh_etag_304_and_gzip(client: TestClient, served: Served) -> None:
    r = client.get(URL, headers={"Accept-Encoding": "gzip"})
    assert r.status_code == 200 and r.headers["content-encoding"] == "gzip"
    assert r.headers["vary"] == "Accept-Encoding"
    assert int(r.headers["content-length"]) < len(r.content)  # compressed on the wire
    etag = r.headers["etag"]
    assert client.get(URL, headers={"If-None-Match": etag}).status_code == 304
    plain = client.get(URL, headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers and plain.json() == r.json()
    served.feed_next(1)  # a new sample moves the live field
    changed = client.get(URL, headers={"If-None-Match": etag})
    assert changed.status_code == 200 and changed.headers["etag"] != etag


class BlockingField:
    """Wraps a service; ``field()`` waits until released (a slow field build)."""

    def __init__(self, inner: SoftSensorService) -> None:
        self.inner = inner
        self.release = threading.Event()

    def field(self, at: Any) -> FieldSnapshot:
        self.release.wait(10.0)
        return self.inner.field(at)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_excess_field_requests_are_shed_with_retry_after(ro_service: SoftSensorService) -> None:
    slow = BlockingField(ro_service)
    app: FastAPI = create_app(Settings(), slow)  # type: ignore[arg-type]
    with TestClient(app) as client:
        statuses: list[int] = []
        threads = [
            threading.Thread(target=lambda: statuses.append(client.get(URL).status_code)) for _ in range(4)
        ]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 10.0
        while getattr(app.state, "field_gate", None) is None or app.state.field_gate.in_progress < 4:
            assert time.monotonic() < deadline, "4 field requests never got in progress"
            time.sleep(0.01)
        shed = client.get(URL, params={"format": "points", "points": "0.03,0.1"})
        assert shed.status_code == 503 and shed.headers["retry-after"] == "1"
        assert shed.json()["error"]["code"] == "overloaded"
        assert client.get("/api/v1/chtc").status_code == 200  # /chtc is not held up meanwhile
        slow.release.set()
        for t in threads:
            t.join(10.0)
        assert statuses == [200] * 4
        assert client.get(URL).status_code == 200 and app.state.field_gate.in_progress == 0
