"""An H that is no estimate gives the live state the guessed considered error (issue 40): a fit's H on its
search box's bound, and a speed map's H outside the reduced model's box (the map extrapolated; the live state
takes it clipped into the box). Seen in the robustness bench's airflow family, where the map put H1 at 500
and H5 at 1 W/(m²·K) after H7 doubled mid-shift (docs/design/robustness.md)."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta

import numpy as np

from service.contracts.records import IdentificationData
from service.contracts.snapshots import ConditionSnapshot, ConditionState
from service.core.machine import ServiceCore
from service.core.maptrack import into_box
from service.defaults import H_FORM_SD_LN, H_NO_BASELINE_SD_LN
from service.estimate.state import GUESSED_H_REL
from service.host.runtime import core_config
from service.serve.views import data_to_record
from service.settings import Settings

T = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
H = np.array([88.2, 46.3, 68.5, 46.7, 52.1, 70.2, 16.5])
BAND = H * math.exp(1.96 * 0.1)  # σ(ln H) = 0.1 as h_rel_from_ci reads it


def test_into_box_clips_and_marks_only_a_band_wholly_outside() -> None:
    h = np.array([500.0, 1.0, 5.0, 200.0, 60.0, 199.9, 4.1])
    lo, hi = h / 1.2, h * 1.2  # H7's band (3.4..4.9) lies outside the box, too; H2's (0.8..1.2) also
    lo[6], hi[6] = 2.0, 8.0  # ...unless it reaches into it
    inside, guessed = into_box(h, lo, hi, (5.0, 200.0))
    np.testing.assert_array_equal(inside, [200.0, 5.0, 5.0, 200.0, 60.0, 199.9, 5.0])
    np.testing.assert_array_equal(guessed, [True, True, False, False, False, False, False])
    assert h[0] == 500.0  # the caller's array is left as it was


def test_a_guessed_h_gets_the_guessed_error_and_the_others_their_band(loaded_model) -> None:  # type: ignore[no-untyped-def]
    parts = ServiceCore(core_config(Settings()), model=loaded_model)._p
    mask = np.array([True, False, False, False, True, False, False])
    rel = parts.h_rel_for(H, BAND, mask)
    band = math.sqrt(0.1**2 + H_FORM_SD_LN**2 + H_NO_BASELINE_SD_LN**2)  # no baseline yet
    np.testing.assert_allclose(rel, np.where(mask, GUESSED_H_REL, band), rtol=1e-6)
    np.testing.assert_allclose(parts.h_rel_for(H, BAND), band, rtol=1e-6)  # no mask: the band alone


def test_a_served_fit_with_an_h_on_its_bound_gives_the_live_state_the_guessed_error(loaded_model) -> None:  # type: ignore[no-untyped-def]
    parts = ServiceCore(core_config(Settings()), model=loaded_model)._p
    cond = ConditionSnapshot(
        id=1, speed_rpm=4000.0, torque_nm=5.0, ambient_c=22.0, since=T, state=ConditionState.STABLE
    )
    data = IdentificationData(
        id=1,
        condition_id=1,
        started_at=T,
        finished_at=T,
        window_start=T - timedelta(minutes=10),
        window_end=T,
        reason="scheduled",
        outcome="ok",
        method="hybrid",
        model_version="m",
        h=H.tolist(),
        ci95_lo=(H * math.exp(-1.96 * 0.1)).tolist(),
        ci95_hi=BAND.tolist(),
        identified=[False, True, True, True, True, True, True],
        f=0.0225,
        fit=1 / 1.0225,
        rmse_c=0.15,
        diagnostics={"at_bound": [True, False, False, False, False, False, False]},
    )
    parts.serve((data_to_record(data, cond), None))
    considered = np.array(parts.live._noise.h_rel)  # what the filter's cross-covariance is scaled by
    assert considered[0] == GUESSED_H_REL
    band = math.sqrt(0.1**2 + H_FORM_SD_LN**2 + H_NO_BASELINE_SD_LN**2)
    np.testing.assert_allclose(considered[1:], band, rtol=1e-6)
