"""A plant's own mechanics (``model.plantmech``): the draw, the nominal, and what each parameter does."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies.growth_check import AMBIENT_C, steady_field
from model.fem import FEModel
from model.geometry import SpindleSpec, spec_from_dict
from model.plant import VirtualPlant
from model.plantmech import (
    ALPHA_REL,
    PlantMechanics,
    PlantMechanicsError,
    alpha_region_scales,
    build_plant_growth,
    mechanics_for_seed,
)
from model.thermoelastic import GrowthModel, build_growth_model

from .conftest import packaged_doc

NOSE = 0  # nose_axial


@pytest.fixture(scope="module")
def rise(spec: SpindleSpec, fe: FEModel) -> np.ndarray:
    """Steady 5000 rpm rise over 20 °C (Table 4 H): the docs' variant table's field."""
    return np.asarray(steady_field(spec, fe, 5000.0) - AMBIENT_C)


def _growth(spec: SpindleSpec, fe: FEModel, rise: np.ndarray, **kw: float) -> np.ndarray:
    return np.asarray(build_plant_growth(spec, fe, PlantMechanics(**kw)).growth_um(rise, 0.0))


# ---------------------------------------------------------------- the draw


def test_draw_is_reproducible_per_seed_and_differs_between_seeds() -> None:
    assert mechanics_for_seed(300) == mechanics_for_seed(300)
    assert PlantMechanics.draw(np.random.default_rng(5)) == PlantMechanics.draw(np.random.default_rng(5))
    draws = {mechanics_for_seed(s) for s in range(20)}
    assert len(draws) == 20


def test_draws_lie_in_their_ranges_and_span_them() -> None:
    draws = [mechanics_for_seed(s) for s in range(300)]
    s = np.array([d.restraint for d in draws])
    a = np.array([[d.alpha_shaft, d.alpha_housing] for d in draws])
    assert np.all((s >= 0) & (s < 1))
    assert s.min() < 0.05 and s.max() > 0.95  # uniform over free..held
    assert np.all(np.abs(a - 1.0) <= ALPHA_REL)
    assert np.all(a.min(axis=0) < 1 - 0.9 * ALPHA_REL) and np.all(a.max(axis=0) > 1 + 0.9 * ALPHA_REL)
    assert abs(np.corrcoef(a.T)[0, 1]) < 0.2  # drawn independently


@pytest.mark.parametrize(
    "kw", [{"restraint": -0.1}, {"restraint": 1.2}, {"alpha_shaft": 2.0}, {"alpha_housing": float("nan")}]
)
def test_out_of_range_mechanics_are_rejected(kw: dict[str, float]) -> None:
    with pytest.raises(PlantMechanicsError):
        PlantMechanics(**kw)


def test_spring_is_zero_free_and_infinite_held() -> None:
    assert PlantMechanics(restraint=0.0).spring_pa_per_m == 0.0
    assert PlantMechanics(restraint=1.0).spring_pa_per_m == np.inf
    assert PlantMechanics(restraint=0.5).spring_pa_per_m == pytest.approx(1e12)


def test_alpha_scales_go_to_shaft_and_housing_materials_only(spec: SpindleSpec) -> None:
    scales = dict(zip([g.name for g in spec.regions], alpha_region_scales(spec, 1.02, 0.97), strict=True))
    assert scales["shaft_body"] == scales["shaft_nose"] == 1.02
    assert scales["housing"] == scales["front_end_cap"] == scales["rear_end_cap"] == 0.97
    assert scales["front_bearing_a"] == scales["pulley"] == scales["spacer"] == 1.0  # spacer: "bearing"


# ---------------------------------------------------------------- the nominal is the old growth


def test_nominal_mechanics_give_the_old_growth(spec: SpindleSpec, fe: FEModel, growth: GrowthModel) -> None:
    nominal = build_plant_growth(spec, fe, PlantMechanics.nominal(spec))
    np.testing.assert_allclose(nominal.operators, growth.operators, rtol=0, atol=1e-12)
    plant = VirtualPlant(spec, fe=fe)  # mechanics None: the description's own
    rng = np.random.default_rng(0)
    field = 20.0 + rng.normal(size=(3, fe.n_nodes))
    np.testing.assert_allclose(plant.growth_um(field, 20.0), growth.growth_um(field, 20.0), atol=1e-12)


def test_nominal_follows_the_description_s_fix(fe: FEModel) -> None:
    doc = packaged_doc()
    doc["mechanics"]["mount"]["fix"] = "axial_radial"
    held_spec = spec_from_dict(doc)
    assert PlantMechanics.nominal(held_spec).restraint == 1.0
    old = build_growth_model(held_spec, fe)
    new = build_plant_growth(held_spec, fe, PlantMechanics.nominal(held_spec))
    np.testing.assert_allclose(new.operators, old.operators, rtol=0, atol=1e-12)


def test_plant_uses_its_drawn_mechanics(spec: SpindleSpec, fe: FEModel, growth: GrowthModel) -> None:
    mech = mechanics_for_seed(301)
    plant = VirtualPlant(spec, fe=fe, mechanics=mech)
    expected = build_plant_growth(spec, fe, mech)
    np.testing.assert_allclose(plant.growth.operators, expected.operators, atol=1e-12)
    assert not np.allclose(plant.growth.operators[NOSE], growth.operators[NOSE], rtol=1e-3)


# ---------------------------------------------------------------- what each parameter does


def test_holding_the_mount_radially_lowers_the_nose_growth(
    spec: SpindleSpec, fe: FEModel, rise: np.ndarray
) -> None:
    """docs/design/growth.md: free +8.2 µm, held −2.6 µm at steady 5000 rpm; the spring goes between."""
    values = [_growth(spec, fe, rise, restraint=s)[NOSE] for s in (0.0, 0.25, 0.5, 0.75, 1.0)]
    assert values[0] == pytest.approx(8.2, abs=0.3)
    assert values[-1] == pytest.approx(-2.6, abs=0.3)
    assert np.all(np.diff(values) < -1.0)  # monotone, each quarter moves it by > 1 µm
    # K_HALF puts the half-way point at s = 0.5: the growth is nearly linear in s
    assert values[2] == pytest.approx(0.5 * (values[0] + values[-1]), abs=0.1 * (values[0] - values[-1]))


def test_growth_is_linear_in_each_alpha_factor(spec: SpindleSpec, fe: FEModel, rise: np.ndarray) -> None:
    base = _growth(spec, fe, rise)
    d_shaft = _growth(spec, fe, rise, alpha_shaft=1.05) - base
    d_housing = _growth(spec, fe, rise, alpha_housing=1.05) - base
    both = _growth(spec, fe, rise, alpha_shaft=0.97, alpha_housing=1.04)
    np.testing.assert_allclose(both, base - 0.6 * d_shaft + 0.8 * d_housing, atol=1e-9)


def test_alpha_factors_scale_the_growth_proportionally(
    spec: SpindleSpec, fe: FEModel, rise: np.ndarray, growth: GrowthModel
) -> None:
    """Both α + 5 %: every output within 5 ± 2 % of its nominal (bearings, pulley keep their α); the shaft's
    α lengthens the nose, the housing's (between mount and locating bearing) pulls it back."""
    base = _growth(spec, fe, rise)
    both = _growth(spec, fe, rise, alpha_shaft=1.05, alpha_housing=1.05)
    np.testing.assert_allclose(both / base, 1.05, atol=0.02)
    assert _growth(spec, fe, rise, alpha_shaft=1.05)[NOSE] > base[NOSE]
    assert _growth(spec, fe, rise, alpha_housing=1.05)[NOSE] < base[NOSE]


def test_bench_plant_draws_per_seed_or_keeps_the_nominal(spec: SpindleSpec) -> None:
    from benchmarks.compensation_run import Plant

    drawn, nominal = Plant(spec), Plant(spec, mechanics="nominal")
    assert drawn.mechanics(7) == mechanics_for_seed(7) != drawn.mechanics(8)
    assert nominal.mechanics(7) == nominal.mechanics(8) == PlantMechanics.nominal(spec)
    with pytest.raises(ValueError, match="plant-mechanics"):
        Plant(spec, mechanics="random")
