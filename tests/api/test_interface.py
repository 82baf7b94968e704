"""service.serve.interface helpers, and the real service's snapshots on the real FE mesh."""

from __future__ import annotations

import importlib
import inspect
from datetime import UTC, datetime

import numpy as np
import pytest

from model.geometry import load_spindle
from service.contracts.snapshots import FieldSnapshot
from service.serve.histogram import Histogram
from service.serve.interface import ChtcService
from simulator.served import Served


def _linear_field(nodes: np.ndarray) -> np.ndarray:
    return 20.0 + 150.0 * nodes[:, 0] - 12.0 * nodes[:, 1]


def test_field_evaluate_reproduces_a_linear_field_exactly_inside_and_nan_outside(served_ro: Served) -> None:
    mesh = served_ro.service.field("now")
    f = FieldSnapshot(datetime.now(UTC), "now", mesh.nodes_rz, mesh.triangles, _linear_field(mesh.nodes_rz))
    r0, r1, z0, z1 = f.bounds_rz
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(r0 - 0.01, r1 + 0.01, 4000), rng.uniform(z0 - 0.01, z1 + 0.01, 4000)]
    got = f.evaluate(pts)
    inside = ~np.isnan(got)
    np.testing.assert_allclose(got[inside], _linear_field(pts[inside]), atol=1e-9)
    # the section is the union of the spindle description's rectangles: a point 1 mm inside one of them is
    # inside, a point more than 1 mm away from all of them is outside
    margin = 1e-3
    dist = np.full(len(pts), np.inf)
    for reg in load_spindle().regions:
        dr = np.maximum(np.maximum(reg.r0_m - pts[:, 0], pts[:, 0] - reg.r1_m), 0.0)
        dz = np.maximum(np.maximum(reg.z0_m - pts[:, 1], pts[:, 1] - reg.z1_m), 0.0)
        dist = np.minimum(dist, np.hypot(dr, dz))
        deep = (pts[:, 0] > reg.r0_m + margin) & (pts[:, 0] < reg.r1_m - margin)
        deep &= (pts[:, 1] > reg.z0_m + margin) & (pts[:, 1] < reg.z1_m - margin)
        assert inside[deep].all(), reg.name
    assert not inside[dist > margin].any()
    assert inside.any() and (dist > margin).any()


def test_histogram_is_cumulative() -> None:
    h = Histogram((0.1, 1.0))
    for v in (0.05, 0.5, 0.7, 5.0):
        h.observe(v)
    snap = h.snapshot()
    assert snap.counts == (1, 3) and snap.count == 4 and snap.sum == pytest.approx(6.25)


def test_the_real_service_satisfies_the_protocol(served_ro: Served) -> None:
    assert isinstance(served_ro.service, ChtcService)


def test_steady_field_and_predictions_on_the_real_fe_mesh(served_ro: Served) -> None:
    svc = served_ro.service
    f = svc.field("steady")
    ambient = svc.condition().ambient_c
    assert f.temps_c.shape == (len(f.nodes_rz),)
    assert f.temps_c.min() >= ambient - 1e-6  # heat only flows out of the bearings
    assert f.temps_c.max() > ambient + 1.0
    assert f.temps_c.max() > svc.field("now").temps_c.max()  # 22 min from cold: still heating up
    readings = svc.sensors()
    assert len(readings) == 32
    pred = np.array([r.predicted_c for r in readings], dtype=float)
    assert np.isfinite(pred).all()  # every sensor sits on the section
    now = svc.field("now").evaluate(np.array([[r.r_m, r.z_m] for r in readings]))
    np.testing.assert_allclose(pred, now, atol=1e-6)


def _protocol_methods() -> dict[str, inspect.Signature]:
    return {
        name: inspect.signature(member)
        for name, member in vars(ChtcService).items()
        if callable(member) and not name.startswith("_")
    }


def test_the_service_matches_the_protocol_signatures() -> None:
    cls = importlib.import_module("service.shell.service").SoftSensorService
    for name, sig in _protocol_methods().items():
        assert hasattr(cls, name), f"SoftSensorService lacks {name}()"
        got = inspect.signature(getattr(cls, name))
        want = [(p.name, p.kind) for p in sig.parameters.values()]
        have = [(p.name, p.kind) for p in got.parameters.values()]
        assert have == want, f"SoftSensorService.{name}{got} != ChtcService.{name}{sig}"
