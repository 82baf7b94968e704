"""``VirtualPlant.run(keep_fields_every=k)``: the full plant-mesh field every k samples, same sensors."""

from __future__ import annotations

import numpy as np
import pytest

from model.fem import build_fe_model
from model.geometry import SpindleSpec
from model.plant import PlantError, Segment, VirtualPlant

PROFILE = [
    Segment(70.0, 0.0, 0.0, 21.0),
    Segment(400.0, 5000.0, 8.0, 21.0),
    Segment(130.0, 2000.0, 4.0, 22.0),
]


@pytest.fixture(scope="module")
def plant(spec: SpindleSpec) -> VirtualPlant:
    return VirtualPlant(spec, fe=build_fe_model(spec, mesh_size_m=0.005), seed=3)


@pytest.mark.parametrize("every", [1, 4, 6])
def test_kept_fields_give_the_sensors_and_change_nothing(plant: VirtualPlant, every: int) -> None:
    plain = plant.run(PROFILE)
    kept = plant.run(PROFILE, keep_fields_every=every)
    assert np.allclose(kept.truth_c, plain.truth_c, rtol=0, atol=1e-12)
    assert np.array_equal(kept.temps_c, plain.temps_c)  # same noise draws
    n = len(plain.times_s)
    assert np.array_equal(kept.field_times_s, plain.times_s[::every][: (n - 1) // every + 1])
    assert kept.fields_c.shape == (len(kept.field_times_s), plant.fe.n_nodes)
    at = (kept.field_times_s / 10.0).astype(int)
    assert np.allclose(kept.fields_c @ plant.fe.sensor_op.T, plain.truth_c[at], rtol=0, atol=1e-10)
    assert np.allclose(kept.fields_c[0], 21.0)
    if (n - 1) % every == 0:
        assert np.allclose(kept.fields_c[-1], plain.final_field_c, rtol=0, atol=1e-12)


def test_steady_shortcut_keeps_the_converged_field(spec: SpindleSpec, plant: VirtualPlant) -> None:
    long = [Segment(6 * 3600.0, 3000.0, 5.0, 21.0)]  # converges: the plant fills the rest of the segment
    run = plant.run(long, keep_fields_every=30)
    assert np.allclose(run.fields_c @ plant.fe.sensor_op.T, run.truth_c[::30], rtol=0, atol=1e-10)
    assert np.allclose(run.fields_c[-1], run.final_field_c, rtol=0, atol=1e-12)


def test_negative_period_is_refused(plant: VirtualPlant) -> None:
    with pytest.raises(PlantError, match="keep_fields_every"):
        plant.run(PROFILE, keep_fields_every=-1)
