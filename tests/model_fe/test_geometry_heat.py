"""Spindle description loading/validation, mesh bookkeeping, heat sources, inputs, empirical H."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from model.empirical import air_properties, churchill_chu_nusselt, empirical_h, forced_nusselt
from model.fem import FEError, build_fe_model
from model.geometry import BearingSpec, SpindleError, load_spindle, spec_from_dict
from model.heat import bearing_heat_w, friction_moment_nmm
from model.inputs import InputError, InputSeries, inputs_from_operation

from .cases import L_M, cylinder_doc, packaged_doc


def test_packaged_spindle_loads(spec) -> None:  # type: ignore[no-untyped-def]
    assert [z.name for z in spec.zones] == ["H1", "H2", "H3", "H4", "H5", "H6", "H7"]
    assert [s.channel for s in spec.sensors] == list(range(1, 33))
    assert sum(s.role == "bearing" for s in spec.sensors) == 12
    assert sorted(spec.test_point_channels) == [1, 3, 5, 7]
    assert 0.55 < spec.length_m < 0.65
    assert spec.h_box == (5.0, 200.0)


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (("sensors", 4, "r_m"), -0.01, r"^sensors\[4\]\.r_m: must be > 0"),
        (("sensors", 4, "r_m"), 0.3, r"^sensors\[4\]\.r_m: point .* not inside any solid region"),
        (("sensors", 2, "role"), "rotor", r"^sensors\[2\]\.role: must be .bearing., .housing. or .shaft."),
        (("sensors", 2, "channel"), 9, r"^sensors\[2\]\.channel: expected 3"),
        (("regions", 1, "material"), "unobtainium", r"^regions\[1\]\.material: unknown material"),
        (("regions", 0, "r1_m"), 0.0, r"^regions\[0\]\.r1_m: must be > 0"),
        (("regions", 2, "z1_m"), 0.1, r"^regions\[2\]\.z1_m: must be > z0_m"),
        (("materials", "steel", "k_w_mk"), "hot", r"^materials\.steel\.k_w_mk: must be a finite number"),
        (("bearings", "front", "dm_mm"), 0, r"^bearings\.front\.dm_mm: must be > 0"),
        (("zones", 3, "name"), "H9", r"^zones\[3\]\.name: expected 'H4'"),
        (
            ("zones", 0, "segments"),
            [[[0.0, 0.0], [0.1, 0.2]]],
            r"^zones\[0\]\.segments\[0\]: must be axis-aligned",
        ),
        (("h_box",), [200.0, 5.0], r"^h_box:"),
        (("sensors", 5, "name"), "front_bearing_a_outer_ring", r"^sensors\[5\]\.name: duplicate"),
        (("regions", 3, "name"), "shaft_body", r"^regions\[3\]\.name: duplicate"),
    ],
)
def test_validation_errors_name_the_field(path: tuple, value: object, message: str) -> None:  # type: ignore[type-arg]
    doc = packaged_doc()
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    with pytest.raises(SpindleError, match=message):
        spec_from_dict(doc)


def test_missing_field_and_count_errors() -> None:
    doc = packaged_doc()
    del doc["sensors"][7]["z_m"]
    with pytest.raises(SpindleError, match=r"^sensors\[7\]\.z_m: missing"):
        spec_from_dict(doc)
    doc = packaged_doc()
    doc["sensors"].pop()
    with pytest.raises(SpindleError, match=r"^sensors: expected 32"):
        spec_from_dict(doc)


def test_load_errors_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed\n")
    with pytest.raises(SpindleError, match="invalid TOML"):
        load_spindle(bad)
    with pytest.raises(SpindleError, match="cannot read"):
        load_spindle(tmp_path / "missing.toml")


def _segment_area(seg) -> float:  # type: ignore[no-untyped-def]
    if seg.r0_m == seg.r1_m:
        return 2 * math.pi * seg.r0_m * abs(seg.z1_m - seg.z0_m)
    return math.pi * abs(seg.r1_m**2 - seg.r0_m**2)


def test_zone_areas_equal_the_segments_true_axisymmetric_areas(spec, coarse_fe) -> None:  # type: ignore[no-untyped-def]
    expected = [sum(_segment_area(s) for s in z.segments) for z in spec.zones]
    assert np.allclose(coarse_fe.zone_area_m2, expected, rtol=1e-12)
    assert coarse_fe.adiabatic_area_m2 == 0.0  # every outer surface of the packaged spindle is in a zone


def test_mesh_volume_and_heat_capacity(spec, coarse_fe) -> None:  # type: ignore[no-untyped-def]
    volumes = {}
    for g in spec.regions:  # regions of the packaged file do not overlap
        volumes[g.name] = math.pi * (g.r1_m**2 - g.r0_m**2) * (g.z1_m - g.z0_m)
    capacity = sum(
        volumes[g.name] * spec.materials[g.material].rho_kg_m3 * spec.materials[g.material].c_j_kgk
        for g in spec.regions
    )
    ones = np.ones(coarse_fe.n_nodes)
    assert ones @ coarse_fe.E @ ones == pytest.approx(capacity, rel=1e-12)


def test_sensor_operator_interpolates_linear_fields_exactly(spec, coarse_fe) -> None:  # type: ignore[no-untyped-def]
    r, z = coarse_fe.nodes_rz.T
    field = 3.0 + 100.0 * r - 20.0 * z
    expected = [3.0 + 100.0 * s.r_m - 20.0 * s.z_m for s in spec.sensors]
    assert np.allclose(coarse_fe.sensors(field), expected, atol=1e-12)
    assert np.allclose(coarse_fe.sensor_op.sum(axis=1), 1.0)


def test_palmgren_heat_matches_hand_calculation() -> None:
    b = BearingSpec(f0=1.5, nu_mm2_s=12.0, dm_mm=90.0, f1=0.0004, p1_n=1000.0, load_per_torque_n_per_nm=10.0)
    # n = 4000 rpm, torque 20 N m: nu n = 48000 >= 2000
    m0 = 1e-7 * 1.5 * 48000 ** (2 / 3) * 90.0**3
    m1 = 0.0004 * (1000.0 + 10.0 * 20.0) * 90.0
    assert friction_moment_nmm(4000, 20.0, b) == pytest.approx(m0 + m1, rel=1e-12)
    assert bearing_heat_w(4000, 20.0, b) == pytest.approx(1.047e-4 * 4000 * (m0 + m1), rel=1e-12)
    assert bearing_heat_w(4000, -20.0, b) == bearing_heat_w(4000, 20.0, b)
    # low-speed branch nu n < 2000: M0 = 160e-7 f0 dm^3
    m_low = 160e-7 * 1.5 * 90.0**3 + 0.0004 * 1000.0 * 90.0
    assert bearing_heat_w(100, 0.0, b) == pytest.approx(1.047e-4 * 100 * m_low, rel=1e-12)
    assert bearing_heat_w(0, 0.0, b) == 0.0
    assert np.allclose(bearing_heat_w(np.array([0.0, 4000.0]), 20.0, b), [0.0, bearing_heat_w(4000, 20.0, b)])


def test_inputs_from_operation(spec) -> None:  # type: ignore[no-untyped-def]
    speed = np.array([0.0, 3000.0, 6000.0])
    inputs = inputs_from_operation(spec, dt_s=10.0, speed_rpm=speed, torque_nm=5.0, ambient_c=21.0)
    assert inputs.n_steps == 3 and np.all(inputs.ambient_c == 21.0)
    assert inputs.q_front_w[0] == 0.0 and inputs.q_front_w[2] > inputs.q_front_w[1] > 0
    assert inputs.q_rear_w[1] == pytest.approx(bearing_heat_w(3000.0, 5.0, spec.bearings.rear))
    assert np.allclose(inputs.times_s, [0, 10, 20, 30])
    with pytest.raises(InputError, match="lengths differ"):
        inputs_from_operation(spec, dt_s=10.0, speed_rpm=speed, torque_nm=np.ones(2), ambient_c=21.0)
    with pytest.raises(InputError, match=r"^q_rear_w:"):
        InputSeries(10.0, np.ones(3), np.ones(3), np.ones(2))
    with pytest.raises(InputError, match=r"^dt_s:"):
        InputSeries(0.0, np.ones(3), np.ones(3), np.ones(3))


def test_empirical_correlations(spec) -> None:  # type: ignore[no-untyped-def]
    air = air_properties(25.0)
    assert air.nu_m2_s == pytest.approx(1.56e-5, rel=0.03)  # tables: 1.562e-5 m^2/s at 25 degC
    assert air.k_w_mk == pytest.approx(0.0260, rel=0.03)
    assert forced_nusselt(1e5, 0.71) == pytest.approx(0.664 * 1e5**0.5 * 0.71 ** (1 / 3))
    assert forced_nusselt(1e6, 0.71) == pytest.approx(0.037 * 1e6**0.8 * 0.71 ** (1 / 3))
    # by hand: (0.559/0.71)^(9/16) = 0.8742; 1.8742^(8/27) = 1.2045; (0.6 + 0.387*10/1.2045)^2 = 14.54
    assert churchill_chu_nusselt(1e6, 0.71) == pytest.approx(14.54, abs=0.01)
    h_3000 = empirical_h(spec, 3000.0, 23.2)
    h_6000 = empirical_h(spec, 6000.0, 23.2)
    rotating = np.array([z.rotating for z in spec.zones])
    assert np.all(h_6000[rotating] > h_3000[rotating])  # forced convection grows with speed
    assert np.allclose(h_6000[~rotating], h_3000[~rotating])
    assert np.all((h_3000 > 2.0) & (h_3000 < 200.0))
    z = spec.zones[1]
    v = 2 * math.pi * z.radius_m * 3000 / 60
    re = v * z.diameter_m / air_properties(28.2).nu_m2_s
    assert h_3000[1] == pytest.approx(
        0.664 * re**0.5 * 0.71 ** (1 / 3) * air_properties(28.2).k_w_mk / z.length_m
    )


def test_zone_segment_errors_name_the_zone() -> None:
    doc = cylinder_doc()
    doc["zones"][3]["segments"] = [[[0.02, 0.0], [0.05, 0.0]]]  # H4 now covers H3's facets too
    with pytest.raises(FEError, match=r"^zones\[3\]\.segments: overlap zone H3"):
        build_fe_model(spec_from_dict(doc), mesh_size_m=0.005)
    doc = cylinder_doc()
    doc["zones"][6]["segments"] = [[[0.2, 0.0], [0.2, 0.1]]]  # nowhere near the solid
    with pytest.raises(FEError, match=r"^zones\[6\]\.segments: no boundary facet"):
        build_fe_model(spec_from_dict(doc), mesh_size_m=0.005)


def test_untagged_boundaries_are_adiabatic_and_reported() -> None:
    doc = cylinder_doc()
    doc["zones"][6]["segments"] = [[[0.045, L_M], [0.05, L_M]]]  # leaves r 0.04..0.045 of the top face free
    fe = build_fe_model(spec_from_dict(doc), mesh_size_m=0.0025)
    assert fe.adiabatic_area_m2 == pytest.approx(math.pi * (0.045**2 - 0.04**2), rel=1e-12)
