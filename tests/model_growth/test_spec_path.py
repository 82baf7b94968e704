"""The [mechanics] section and mechanical properties: validation names the field; the 1-D rule is exact
where it should be; the thermal cache key does not see the mechanics."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from benchmarks.studies.growth_path import Band, axial_1d_um, band_integral_m
from model.fem import build_fe_model
from model.geometry import SpindleError, load_spindle, spec_from_dict
from model.thermoelastic import ThermoelasticError, build_growth_model
from tests.model_growth.conftest import packaged_doc


def _edit(path: str, value: Any) -> dict[str, Any]:
    doc = packaged_doc()
    node = doc
    keys = path.split("/")
    for k in keys[:-1]:
        node = node[int(k)] if k.isdigit() else node[k]
    last = keys[-1]
    if value is None:
        del node[last]
    elif last.isdigit():
        node[int(last)] = value
    else:
        node[last] = value
    return doc


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        ("materials/steel/nu", 0.5, "materials.steel.nu"),
        ("materials/steel/alpha_per_k", 11.5, "materials.steel.alpha_per_k"),
        ("materials/steel/e_pa", -1.0, "materials.steel.e_pa"),
        ("materials/cast_iron/e_pa", None, "materials.cast_iron.e_pa: missing"),
        ("mechanics/mount/fix", "radial", "mechanics.mount.fix"),
        ("mechanics/mount/segments", [[0.1, 0.55]], "mechanics.mount.segments[0]"),
        ("mechanics/floating/0/region", "nowhere", "mechanics.floating[0].region"),
        ("mechanics/floating/0/surface", "side", "mechanics.floating[0].surface"),
        ("mechanics/outputs/0/r_m", 0.2, "mechanics.outputs[0].r_m"),
        ("mechanics/outputs/1/name", "nose_axial", "mechanics.outputs[1].name"),
        ("mechanics/outputs/0/component", "hoop", "mechanics.outputs[0].component"),
        ("mechanics/region_material/spacer", "unobtainium", "mechanics.region_material.spacer"),
        ("mechanics/outputs", [], "mechanics.outputs"),
    ],
)
def test_bad_mechanics_names_the_field(path: str, value: Any, field: str) -> None:
    with pytest.raises(SpindleError, match=field.replace("[", r"\[").replace("]", r"\]")):
        spec_from_dict(_edit(path, value))


def test_material_without_mechanics_is_fine_without_a_mechanics_section() -> None:
    doc = packaged_doc()
    del doc["mechanics"]
    for m in doc["materials"].values():
        for k in ("e_pa", "nu", "alpha_per_k"):
            del m[k]
    spec = spec_from_dict(doc)
    assert spec.mechanics is None
    with pytest.raises(ThermoelasticError, match="mechanics"):
        build_growth_model(spec, build_fe_model(spec, mesh_size_m=0.01))


def test_mount_off_the_solid_is_named() -> None:
    spec = spec_from_dict(_edit("mechanics/mount/segments", [[[0.080, 0.300], [0.100, 0.300]]]))
    with pytest.raises(ThermoelasticError, match=r"mechanics\.mount\.segments\[0\]"):
        build_growth_model(spec, build_fe_model(spec, mesh_size_m=0.005))


def test_thermal_repr_unchanged_by_mechanics() -> None:
    """The reduced model's cache key hashes repr(spec): mechanics must not invalidate thermal caches."""
    spec = load_spindle()
    doc = packaged_doc()
    del doc["mechanics"]
    for m in doc["materials"].values():
        for k in ("e_pa", "nu", "alpha_per_k"):
            del m[k]
    assert repr(spec) == repr(spec_from_dict(doc))
    assert "e_pa" not in repr(spec)


def test_one_d_rule_is_exact_for_uniform_alpha_and_rise() -> None:
    doc = packaged_doc()
    for m in doc["materials"].values():
        m["alpha_per_k"] = 11.5e-6
    spec = spec_from_dict(doc)
    fe = build_fe_model(spec, mesh_size_m=0.005)
    rise = np.full(fe.n_nodes, 10.0)
    gm = build_growth_model(spec, fe)
    one_d = axial_1d_um(
        spec, fe, rise, housing=Band(0.065, 0.100, 0.505, 0.550), shaft=Band(0.0, 0.040, 0.505, 0.610)
    )
    assert one_d == pytest.approx(gm.as_dict(gm.growth_um(rise, 0.0))["nose_axial"], rel=1e-9)


def test_band_integral_of_a_linear_rise(spec) -> None:  # type: ignore[no-untyped-def]
    fe = build_fe_model(spec, mesh_size_m=0.005)
    rise = 100.0 * fe.nodes_rz[:, 1]  # dT = 100 z: exact in P1, integral alpha * 50 (z1^2 - z0^2)
    got = band_integral_m(spec, fe, rise, Band(0.0, 0.04, 0.2, 0.4), n_z=401)
    assert got == pytest.approx(11.5e-6 * 50.0 * (0.4**2 - 0.2**2), rel=1e-6)


def test_section_sketch_marks_mount_floating_surface_and_outputs(spec) -> None:  # type: ignore[no-untyped-def]
    from benchmarks.studies.growth_check import section_sketch

    text = section_sketch(spec)
    assert text.count("*") == len(spec.mechanics.outputs)
    assert text.splitlines()[0].count("v") == 1
    assert "~~~~~" in text and text.splitlines()[-2].endswith(" axis")


def test_bench_model_growth_figures(spec) -> None:  # type: ignore[no-untyped-def]
    from benchmarks.model import _growth_figures

    res = _growth_figures(build_fe_model(spec, mesh_size_m=0.005), spec)
    assert res["growth_outputs"][0] == "nose_axial"
    assert res["growth_build_s"] > 0 and res["growth_eval_us"] > 0 and res["growth_eval_reduced_us"] > 0
