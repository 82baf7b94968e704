"""Options and errors of the identification: data checks, offsets, bearing loads, FE re-check, paper stop."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from model.identify import (
    IdentificationError,
    IdentifyOptions,
    InsufficientDataError,
    Window,
    baseline_offsets,
    identify,
)
from model.inputs import InputSeries
from model.plant import Segment, VirtualPlant
from tests.identify.conftest import Condition


def test_too_little_data_raises_typed_errors(model: Any, cond3000: Condition) -> None:
    w = cond3000.window
    short = Window(w.inputs.slice(0, 10), w.measured_c[:11], w.mask, w.t0)
    with pytest.raises(InsufficientDataError, match="samples"):
        identify(model.rom, short, rng=0, spec=model.spec)
    few = np.zeros(32, dtype=bool)
    few[:3] = True
    with pytest.raises(InsufficientDataError, match="channels"):
        identify(model.rom, replace(w, mask=few), rng=0, spec=model.spec)
    gaps = w.measured_c.copy()
    gaps[20:] = np.nan  # the DAQ stopped after 200 s
    with pytest.raises(InsufficientDataError, match="samples"):
        identify(model.rom, replace(w, measured_c=gaps), rng=0, spec=model.spec)


def test_bad_arguments_name_the_field(model: Any, cond3000: Condition) -> None:
    w = cond3000.window
    with pytest.raises(IdentificationError, match="method"):
        identify(model.rom, w, rng=0, method="pso", spec=model.spec)
    with pytest.raises(IdentificationError, match="measured_c"):
        identify(model.rom, replace(w, measured_c=w.measured_c[:, :30]), rng=0, spec=model.spec)
    with pytest.raises(IdentificationError, match="warm_start"):
        identify(model.rom, w, rng=0, spec=model.spec, warm_start=[1.0, 2.0])
    with pytest.raises(IdentificationError, match="offsets_c"):
        identify(model.rom, w, rng=0, spec=model.spec, offsets_c=np.zeros(5))
    with pytest.raises(IdentificationError, match="speed_rpm"):
        identify(model.rom, replace(w, speed_rpm=None), rng=0, method="empirical", spec=model.spec)


def test_offsets_zeroed_against_an_equilibrium_baseline(model: Any, cond3000: Condition) -> None:
    offsets = np.random.default_rng(4).choice([-0.3, 0.3], size=32)
    plant = VirtualPlant(model.spec, offsets_c=offsets, seed=5)
    idle = plant.run([Segment(600.0, 0.0, 0.0, 23.2)], dt_s=10.0)  # spindle at rest: everything at ambient
    estimated = baseline_offsets(idle.temps_c, idle.ambient_c[:, None].mean())
    assert np.max(np.abs(estimated - offsets)) < 0.1
    w = replace(cond3000.window, measured_c=cond3000.window.measured_c + offsets)
    raw = identify(model.rom, w, rng=0, spec=model.spec)
    zeroed = identify(model.rom, w, rng=0, spec=model.spec, offsets_c=estimated)
    assert zeroed.f < 0.5 * raw.f
    assert zeroed.sigma_c < 0.2


def test_bearing_heat_scale_factors_are_recovered_jointly(model: Any, cond3000: Condition) -> None:
    w = cond3000.window
    inp = w.inputs
    low = InputSeries(
        inp.dt_s, inp.ambient_c, inp.q_front_w / 1.1, inp.q_rear_w / 1.1
    )  # model assumes 10 % less
    res = identify(model.rom, replace(w, inputs=low), rng=0, spec=model.spec, estimate_loads=True)
    assert res.load_scale is not None and res.load_scale_ci95 is not None
    assert np.all(np.abs(res.load_scale - 1.1) < 0.05), res.load_scale
    assert np.all((res.load_scale_ci95[:, 0] <= 1.1) & (res.load_scale_ci95[:, 1] >= 1.1))


def test_full_fe_recheck_agrees_with_the_reduced_model(model: Any, cond3000: Condition) -> None:
    res = identify(model.rom, cond3000.window, rng=0, spec=model.spec, fe=model.fe)
    assert res.fe_check is not None
    assert abs(res.fe_check["rmse_diff_c"]) < 0.03
    assert res.fe_check["rmse_rom_c"] == pytest.approx(np.sqrt(res.f), rel=1e-6)


def test_paper_stop_rule_fit_above_one_half(model: Any, cond3000: Condition) -> None:
    full = identify(model.rom, cond3000.window, rng=2, method="igwo", spec=model.spec)
    paper = identify(
        model.rom,
        cond3000.window,
        rng=2,
        method="igwo",
        spec=model.spec,
        options=IdentifyOptions(fun_target=1.0),
    )
    assert paper.fit > 0.5
    assert paper.nfev < full.nfev
    assert "fun_target" in paper.message


def test_start_field_offset_is_fitted_jointly(model: Any, cond3000: Condition) -> None:
    """A start field 0.2 °C too warm everywhere (a live state's common error) biases H unless the uniform
    shift is fitted with them; fitted, the shift comes back as −0.2 °C within its CI and H as without it."""
    w = cond3000.window
    off = replace(w, t0=np.asarray(w.t0, dtype=float) + 0.2)
    exact = identify(model.rom, w, rng=0, spec=model.spec)
    biased = identify(model.rom, off, rng=0, spec=model.spec)
    fitted = identify(model.rom, off, rng=0, spec=model.spec, estimate_t0_shift=True)
    assert fitted.t0_shift_c is not None and fitted.t0_shift_ci95 is not None
    assert abs(fitted.t0_shift_c + 0.2) < 0.02, fitted.t0_shift_c
    assert fitted.t0_shift_ci95[0] <= -0.2 <= fitted.t0_shift_ci95[1]
    assert exact.t0_shift_c is None and exact.t0_shift_ci95 is None
    assert "start field offset -0.2" in fitted.message and "offset" not in exact.message
    assert fitted.sigma_c < 0.9 * biased.sigma_c  # the offset shows in the residuals of the biased fit
    err_fitted = np.abs(fitted.h - cond3000.h_true) / cond3000.h_true
    err_exact = np.abs(exact.h - cond3000.h_true) / cond3000.h_true
    assert np.median(err_fitted) < np.median(err_exact) + 0.05


def test_warm_start_fills_the_loads_and_the_shift(model: Any, cond3000: Condition) -> None:
    w = cond3000.window
    prior = identify(model.rom, w, rng=0, spec=model.spec)
    both = identify(
        model.rom, w, rng=1, spec=model.spec, warm_start=prior, estimate_loads=True, estimate_t0_shift=True
    )
    assert both.theta.size == 10 and both.load_scale is not None and both.t0_shift_c is not None
    with pytest.raises(IdentificationError, match="warm_start: expected 7 or 9 or 10"):
        identify(
            model.rom,
            w,
            rng=0,
            spec=model.spec,
            warm_start=np.ones(8),
            estimate_loads=True,
            estimate_t0_shift=True,
        )
