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
from model.locator import TriangleLocator, locator_for
from service.contracts.snapshots import FieldSnapshot
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.served import Served

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


@pytest.mark.parametrize(
    ("fmt", "with_std"), [("mesh", False), ("grid", False), ("mesh", True), ("grid", True)]
)
def test_fast_bodies_equal_the_schema_serialisation(
    ro_service: SoftSensorService, fmt: str, with_std: bool
) -> None:
    """Also with a 1σ per node (the filtered state's, at=now): ``std_c`` and ``std_max_c`` in both."""
    f = ro_service.field("steady")
    if with_std:
        f = replace(f, std_c=0.05 + 0.01 * np.abs(f.temps_c - f.temps_c.mean()))
    renderer = FieldRenderer(spindle_id="s1")
    if fmt == "mesh":
        fast, reference = renderer.mesh(f), mesh_out(f, spindle_id="s1")
    else:
        fast, reference = renderer.grid(f, 12, 30), grid_out(f, 12, 30, spindle_id="s1")
    assert json.loads(fast.body) == json.loads(reference.model_dump_json())
    assert gzip.decompress(fast.gzip()) == fast.body
    body = json.loads(fast.body)
    assert (body["std_c"] is not None) == with_std and (body["std_max_c"] is not None) == with_std
    if with_std and fmt == "mesh":
        assert body["std_max_c"] == pytest.approx(float(np.max(f.std_c)), abs=1e-4)
        np.testing.assert_allclose(body["std_c"], f.std_c, atol=1e-4)


def test_points_carry_their_1_sigma_and_95_percent(ro_service: SoftSensorService) -> None:
    from api.routers.field import points_out

    f = ro_service.field("steady")
    sd = np.full_like(f.temps_c, 0.1)
    inside = f.nodes_rz[:1] * 0.999 + f.nodes_rz[1:2] * 0.001
    p = points_out(replace(f, std_c=sd), inside, spindle_id="s1").points[0]
    assert p.inside and p.std_c == pytest.approx(0.1, abs=1e-4)
    assert p.ci95_c is not None and p.ci95_c[1] - p.ci95_c[0] == pytest.approx(2 * 1.96 * 0.1, abs=2e-4)
    steady = points_out(f, inside, spindle_id="s1").points[0]
    assert steady.std_c is None  # the steady state has no filtered uncertainty


def test_a_new_field_reuses_the_geometry_and_makes_a_new_body(ro_service: SoftSensorService) -> None:
    f = ro_service.field("now")
    renderer = FieldRenderer(spindle_id="s1")
    a = renderer.mesh(f)
    assert renderer.mesh(replace(f)) is a  # same content: cached
    g = replace(f, temps_c=f.temps_c + 0.5)
    b = renderer.mesh(g)
    assert b.etag != a.etag and renderer.builds == 2
    assert json.loads(b.body) == json.loads(mesh_out(g, spindle_id="s1").model_dump_json())
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
