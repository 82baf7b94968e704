"""service.serve.interface helpers and the in-memory service (with the synthetic and the real FE section)."""

from __future__ import annotations

import importlib
import inspect
from datetime import UTC, datetime

import numpy as np
import pytest

from service.serve.histogram import Histogram
from service.serve.interface import ChtcService, FieldSnapshot
from service.serve.interface_memory import InMemoryService, demo_service, model_section, synthetic_section


def _linear_field(nodes: np.ndarray) -> np.ndarray:
    return 20.0 + 150.0 * nodes[:, 0] - 12.0 * nodes[:, 1]


def test_field_evaluate_reproduces_a_linear_field_exactly_inside_and_nan_outside() -> None:
    sec = synthetic_section()
    f = FieldSnapshot(datetime.now(UTC), "now", sec.nodes_rz, sec.triangles, _linear_field(sec.nodes_rz))
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.01, 0.12, 4000), rng.uniform(-0.01, 0.57, 4000)]
    got = f.evaluate(pts)
    inside = ~np.isnan(got)
    np.testing.assert_allclose(got[inside], _linear_field(pts[inside]), atol=1e-9)
    # a point is inside iff it lies in one of the section's rectangles (the shaft: r <= 0.035, 0 <= z <= 0.5)
    shaft = (pts[:, 0] >= 0) & (pts[:, 0] < 0.034) & (pts[:, 1] > 0.001) & (pts[:, 1] < 0.499)
    assert inside[shaft].all()
    assert not inside[(pts[:, 0] > 0.111) | (pts[:, 1] < -0.001) | (pts[:, 1] > 0.561)].any()
    assert not inside[(pts[:, 0] > 0.061) & (pts[:, 1] > 0.43)].any()  # beyond the housing's end


def test_histogram_is_cumulative() -> None:
    h = Histogram((0.1, 1.0))
    for v in (0.05, 0.5, 0.7, 5.0):
        h.observe(v)
    snap = h.snapshot()
    assert snap.counts == (1, 3) and snap.count == 4 and snap.sum == pytest.approx(6.25)


def test_memory_service_satisfies_the_protocol() -> None:
    assert isinstance(InMemoryService(), ChtcService)


def test_memory_service_with_the_real_fe_section() -> None:
    svc = demo_service(section=model_section(mesh_size_m=None))
    f = svc.field("steady")
    ambient = svc.condition().ambient_c
    assert f.temps_c.shape == (len(f.nodes_rz),)
    assert f.temps_c.min() >= ambient - 1e-6  # heat only flows out of the bearings
    assert f.temps_c.max() > ambient + 1.0
    readings = svc.sensors()
    assert len(readings) == 32
    pred = np.array([r.predicted_c for r in readings], dtype=float)
    assert np.isfinite(pred).all()  # every sensor sits on the section
    now = svc.field("now").evaluate(np.array([[r.r_m, r.z_m] for r in readings]))
    np.testing.assert_allclose(pred, now)


def _protocol_methods() -> dict[str, inspect.Signature]:
    return {
        name: inspect.signature(member)
        for name, member in vars(ChtcService).items()
        if callable(member) and not name.startswith("_")
    }


@pytest.mark.parametrize(
    "impl", ["service.engine.shell:SoftSensorService", "service.serve.interface_memory:InMemoryService"]
)
def test_implementations_match_the_protocol_signatures(impl: str) -> None:
    module, _, cls_name = impl.partition(":")
    cls = getattr(importlib.import_module(module), cls_name)
    for name, sig in _protocol_methods().items():
        assert hasattr(cls, name), f"{cls_name} lacks {name}()"
        got = inspect.signature(getattr(cls, name))
        want = [(p.name, p.kind) for p in sig.parameters.values()]
        have = [(p.name, p.kind) for p in got.parameters.values()]
        assert have == want, f"{cls_name}.{name}{got} != ChtcService.{name}{sig}"
