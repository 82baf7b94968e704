"""H bands without an offset baseline (issue 26, item 6): a start with an empty database on a warm spindle
has no baseline, and its fits' bands missed the truth by up to 2.6σ (docs/design/estimator.md, "Warm restart
with no stored state"); the served bands and the live state's considered H error then carry
``H_NO_BASELINE_SD_LN`` on top of the model-form term, and stop doing so once a baseline exists."""

from __future__ import annotations

import math
from dataclasses import replace
from datetime import UTC, datetime

import numpy as np
import pytest

from service.contracts.calibration import Calibration
from service.core.config import Restored
from service.core.machine import ServiceCore
from service.defaults import H_FORM_SD_LN, H_NO_BASELINE_SD_LN
from service.host.runtime import core_config
from service.settings import Settings


def _calibration() -> Calibration:
    now = datetime(2026, 4, 6, 6, 0, tzinfo=UTC)
    return Calibration(
        offsets_c=np.zeros(32), sd_c=np.full(32, 0.02), t_from=now, t_to=now, samples=30, source="auto"
    )


def test_without_a_baseline_the_served_h_band_carries_the_no_baseline_term(loaded_model) -> None:  # type: ignore[no-untyped-def]
    core = ServiceCore(core_config(Settings()), model=loaded_model)
    assert core.view().calibration is None
    assert core.view().h_form_sd == pytest.approx(math.hypot(H_FORM_SD_LN, H_NO_BASELINE_SD_LN))


def test_a_restored_baseline_or_no_calibration_serves_the_model_form_term_alone(loaded_model) -> None:  # type: ignore[no-untyped-def]
    cfg = core_config(Settings())
    restored = ServiceCore(cfg, model=loaded_model, restored=Restored(calibration=_calibration()))
    assert restored.view().h_form_sd == pytest.approx(H_FORM_SD_LN)
    off = ServiceCore(replace(cfg, calibration=None), model=loaded_model)
    assert off.view().h_form_sd == pytest.approx(H_FORM_SD_LN)


def test_the_live_states_considered_h_error_is_the_served_bands(loaded_model) -> None:  # type: ignore[no-untyped-def]
    """The fit's band, the model-form term and, without a baseline, the no-baseline term, in quadrature: the
    growth's CI (which takes the H error from the live state) admits what the served H band admits."""
    cfg = core_config(Settings())
    h = np.full(7, 40.0)
    hi = h * math.exp(1.96 * 0.1)  # a band of σ(ln H) = 0.1 (h_rel_from_ci reads it with 1.96)
    blind = ServiceCore(cfg, model=loaded_model)._p.h_rel_for(h, hi)
    np.testing.assert_allclose(blind, math.sqrt(0.1**2 + H_FORM_SD_LN**2 + H_NO_BASELINE_SD_LN**2), rtol=1e-6)
    seen = ServiceCore(cfg, model=loaded_model, restored=Restored(calibration=_calibration()))
    np.testing.assert_allclose(seen._p.h_rel_for(h, hi), math.hypot(0.1, H_FORM_SD_LN), rtol=1e-6)
    formless = ServiceCore(
        replace(cfg, live_h_form_sd=0.0), model=loaded_model, restored=Restored(calibration=_calibration())
    )
    np.testing.assert_allclose(formless._p.h_rel_for(h, hi), 0.1, rtol=1e-6)
