"""Virtual plant: ground truth through the paper's tables, determinism, measurement chain, faults."""

from __future__ import annotations

import numpy as np
import pytest

from model.fem import build_fe_model, simulate_sensors
from model.inputs import inputs_from_operation
from model.plant import (
    DEFAULT_SUBSTEPS,
    OPEN_CIRCUIT_C,
    OUT_OF_RANGE_C,
    ChannelFault,
    PlantError,
    Segment,
    VirtualPlant,
    h_true,
)

TABLE4 = [88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54]  # paper, 3000 rpm, 23.2 degC
TABLE10 = [79.75, 46.25, 61.89, 45.31, 46.20, 68.23, 11.12]  # paper, 4000 rpm, 21.8 degC
PROFILE = [Segment(600.0, 3000.0, 5.0, 23.2), Segment(300.0, 5000.0, 8.0, 23.2)]


@pytest.fixture(scope="module")
def plant_fe(spec):  # type: ignore[no-untyped-def]
    return build_fe_model(spec, mesh_size_m=0.006)


def test_h_true_passes_through_tables_4_and_10() -> None:
    assert np.allclose(h_true(3000.0, 23.2, 0.0), TABLE4, atol=1e-10)
    assert np.allclose(h_true(4000.0, 21.8, 12.0), TABLE10, atol=1e-10)


def test_h_true_is_bounded_and_smooth_over_the_operating_range() -> None:
    speeds = np.linspace(0.0, 8000.0, 161)
    for ti in (15.0, 23.2, 35.0):
        h = np.array([h_true(n, ti) for n in speeds])
        assert np.all((h >= 5.0) & (h <= 200.0))
        assert np.abs(np.diff(h, axis=0)).max() < 2.0  # no jumps between 50 rpm steps
    assert np.all(h_true(3000.0, 18.0) > h_true(3000.0, 28.0))  # cooler air, higher H (paper's argument)


def test_plant_is_deterministic_per_seed(spec, plant_fe) -> None:  # type: ignore[no-untyped-def]
    a = VirtualPlant(spec, fe=plant_fe, seed=7).run(PROFILE)
    b = VirtualPlant(spec, fe=plant_fe, seed=7).run(PROFILE)
    c = VirtualPlant(spec, fe=plant_fe, seed=8).run(PROFILE)
    assert np.array_equal(a.temps_c, b.temps_c)
    assert not np.array_equal(a.temps_c, c.temps_c)
    assert np.array_equal(a.truth_c, c.truth_c)


def test_plant_truth_equals_the_fe_model_under_h_true(spec, plant_fe) -> None:  # type: ignore[no-untyped-def]
    run = VirtualPlant(spec, fe=plant_fe, steady_tol_c=0.0).run(PROFILE, dt_s=10.0)
    assert run.times_s.shape == (91,) and run.temps_c.shape == (91, 32)
    assert run.speed_rpm[59] == 3000.0 and run.speed_rpm[60] == 5000.0 and run.speed_rpm[-1] == 5000.0
    assert np.allclose(run.h_true[0], TABLE4)
    # first segment: the FE model itself at the plant's default 4 substeps (2.5 s), driven by the plant's
    # recorded condition and sampled every 10 s
    sub = DEFAULT_SUBSTEPS
    inputs = inputs_from_operation(
        spec,
        dt_s=10.0 / sub,
        speed_rpm=np.repeat(run.speed_rpm[:60], sub),
        torque_nm=np.repeat(run.torque_nm[:60], sub),
        ambient_c=23.2,
    )
    expected, _ = simulate_sensors(plant_fe, TABLE4, inputs, 23.2)
    assert sub >= 4
    assert np.allclose(run.truth_c[:61], expected[::sub], atol=1e-10)
    assert run.truth_c[-1, 0] > run.truth_c[60, 0] > run.truth_c[0, 0]


def test_measurement_noise_quantisation_and_offsets(spec, plant_fe) -> None:  # type: ignore[no-untyped-def]
    offsets = np.linspace(-0.3, 0.3, 32)
    run = VirtualPlant(spec, fe=plant_fe, noise_c=0.15, quant_c=0.01, offsets_c=offsets, seed=1).run(
        [Segment(3600.0, 4000.0, 0.0, 22.0)]
    )
    err = run.temps_c - run.truth_c - offsets
    assert np.std(err) == pytest.approx(0.15, rel=0.05)
    assert np.abs(err.mean(axis=0)).max() < 0.05  # offsets are applied as given
    assert np.allclose(run.temps_c * 100, np.round(run.temps_c * 100), atol=1e-6)
    noiseless = VirtualPlant(spec, fe=plant_fe, noise_c=0.0, quant_c=0.0).run(
        [Segment(60.0, 4000.0, 0.0, 22.0)]
    )
    assert np.array_equal(noiseless.temps_c, noiseless.truth_c)


def test_channel_faults(spec, plant_fe) -> None:  # type: ignore[no-untyped-def]
    faults = [
        ChannelFault(3, "open", 300.0),
        ChannelFault(10, "stuck", 200.0, 500.0),
        ChannelFault(20, "range", 100.0, 150.0),
    ]
    run = VirtualPlant(spec, fe=plant_fe, faults=faults).run(PROFILE)
    t = run.times_s
    assert np.all(run.temps_c[t >= 300, 2] == OPEN_CIRCUIT_C) and np.all(run.status[t >= 300, 2] == 1)
    assert np.all(run.status[t < 300, 2] == 0)
    stuck = run.temps_c[(t >= 200) & (t < 500), 9]
    assert np.all(stuck == run.temps_c[t == 190, 9]) and run.temps_c[t == 500, 9] != stuck[0]
    assert np.all(run.temps_c[(t >= 100) & (t < 150), 19] == OUT_OF_RANGE_C)
    assert np.all(run.status[(t >= 100) & (t < 150), 19] == 2) and run.status[t == 150, 19] == 0


def test_steady_shortcut_and_restart_from_a_field(spec, plant_fe) -> None:  # type: ignore[no-untyped-def]
    long = [Segment(24 * 3600.0, 4000.0, 0.0, 22.0)]
    exact = VirtualPlant(spec, fe=plant_fe, steady_tol_c=0.0, noise_c=0.0).run(long, dt_s=60.0)
    fast = VirtualPlant(spec, fe=plant_fe, steady_tol_c=1e-3, noise_c=0.0).run(long, dt_s=60.0)
    assert np.abs(fast.truth_c - exact.truth_c).max() < 0.02
    more = VirtualPlant(spec, fe=plant_fe, noise_c=0.0).run(long, dt_s=60.0, t0_c=exact.final_field_c)
    assert np.abs(more.truth_c - exact.truth_c[-1]).max() < 0.02  # already at steady state


def test_bad_profiles_name_the_field(spec, plant_fe) -> None:  # type: ignore[no-untyped-def]
    plant = VirtualPlant(spec, fe=plant_fe)
    with pytest.raises(PlantError, match=r"^profile:"):
        plant.run([])
    with pytest.raises(PlantError, match=r"^profile\[1\]\.duration_s"):
        plant.run([Segment(60.0, 1.0, 0.0, 20.0), Segment(1.0, 1.0, 0.0, 20.0)])
    with pytest.raises(PlantError, match=r"^faults\[0\]\.channel"):
        VirtualPlant(spec, fe=plant_fe, faults=[ChannelFault(33, "open", 0.0)])
    with pytest.raises(PlantError, match=r"^offsets_c"):
        VirtualPlant(spec, fe=plant_fe, offsets_c=np.zeros(3))


def test_substeps_reduce_the_time_error(spec, plant_fe) -> None:  # type: ignore[no-untyped-def]
    seg = [Segment(900.0, 6000.0, 0.0, 22.0)]

    def truth(sub: int) -> np.ndarray:
        plant = VirtualPlant(spec, fe=plant_fe, noise_c=0.0, quant_c=0.0, substeps=sub, steady_tol_c=0.0)
        return plant.run(seg, dt_s=10.0).truth_c

    ref = truth(16)
    e1, e4 = np.abs(truth(1) - ref).max(), np.abs(truth(4) - ref).max()
    assert truth(4).shape == ref.shape == (91, 32)
    assert e4 < 0.35 * e1  # backward Euler: error ~ dt
    with pytest.raises(PlantError, match=r"^substeps"):
        VirtualPlant(spec, fe=plant_fe, substeps=0)
