"""An H that is no estimate gives the live state the guessed considered error (issue 40): a fit's H on its
search box's bound, and a speed map's H outside the reduced model's box (the map extrapolated; the live state
takes it clipped into the box). Seen in the robustness bench's airflow family, where the map put H1 at 500
and H5 at 1 W/(m²·K) after H7 doubled mid-shift (docs/design/robustness.md)."""

from __future__ import annotations

import math
from dataclasses import replace
from datetime import UTC, datetime, timedelta

import numpy as np

from model.hmap import NODES
from model.identify_prior import HPrior
from service.contracts.columns import JsonValue
from service.contracts.records import IdentificationData
from service.contracts.snapshots import ConditionSnapshot, ConditionState
from service.core.config import Restored
from service.core.machine import ServiceCore
from service.core.maptrack import into_box
from service.defaults import H_FORM_SD_LN, H_NO_BASELINE_SD_LN
from service.estimate.state import GUESSED_H_REL
from service.host.runtime import core_config
from service.identify.speedmap import SpeedMap
from service.serve.policy import map_verdict
from service.serve.views import chtc_map_snapshot, data_to_record, map_record
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


def _record(cond: ConditionSnapshot, at_bound: list[bool] | None = None):  # type: ignore[no-untyped-def]
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
        diagnostics={} if at_bound is None else {"at_bound": list[JsonValue](at_bound)},
    )
    return data_to_record(data, cond)


COND = ConditionSnapshot(
    id=1, speed_rpm=4000.0, torque_nm=5.0, ambient_c=22.0, since=T, state=ConditionState.STABLE
)


def test_a_map_h_whose_band_lies_outside_the_models_box_is_never_served_identified(loaded_model) -> None:  # type: ignore[no-untyped-def]
    """Seen in the robustness bench (seeds 411-414, map mode): /chtc said H5 = 321 W/(m²·K) identified, with
    its narrow band wholly above the reduced model's box (5-200), which the live state took as a guess."""
    box = loaded_model.ref.h_box
    h = np.array([321.0, 2.0, 68.5, 190.0, 52.1, 70.2, 16.5])  # H1 above, H2 below, H4 near the top
    sd = np.full(7, 0.1)  # narrow: every band within the identification threshold
    prior = HPrior(log_mean=np.log(h), log_cov=np.diag(sd**2), reference_var=np.full(7, 1.0))
    cold = NODES.prior(loaded_model.spec)
    the_map = SpeedMap(
        family="nodes",
        mean=cold.mean,
        cov=cold.cov,
        visited_rpm=np.array([4000.0]),
        visited_s=np.array([600.0]),
        fitted_at=T,
    )
    kw = {"speed_rpm": 4000.0, "ambient_c": 22.0, "condition": COND, "ci_threshold": 0.5, "prior": prior}
    unboxed = map_record(_record(COND), the_map, **kw)  # type: ignore[arg-type]
    assert unboxed.identified.all()  # the band alone says known
    boxed = map_record(_record(COND), the_map, model_box=box, **kw)  # type: ignore[arg-type]
    np.testing.assert_array_equal(boxed.identified, [False, False, True, True, True, True, True])
    np.testing.assert_allclose(boxed.h, h)  # H itself is served as the map has it
    # /chtc/map likewise: no grid speed identified where its band lies wholly outside the box
    # a map 4× the cold one and sure of it: its fastest speeds' H1 above the box, its other H within
    far = replace(the_map, mean=cold.mean + math.log(4.0), cov=cold.cov * 1e-4)
    grid = chtc_map_snapshot(
        far,
        ambient_c=22.0,
        verdict=map_verdict(
            far,
            newest_t=T,
            speed_rpm=4000.0,
            problems=(),
            converging_since=None,
            fresh_s=900.0,
            margin_rpm=300.0,
            min_visit_s=60.0,
        ),
        newest_sample_at=T,
        current_speed_rpm=4000.0,
        ci_threshold=10.0,
        margin_rpm=300.0,
        model_box=box,
    )
    outside = (grid.ci95_hi_w_m2k < box[0]) | (grid.ci95_lo_w_m2k > box[1])
    assert outside.any() and (~outside).any()
    np.testing.assert_array_equal(grid.identified, ~outside)


def test_a_guessed_h_gets_the_guessed_error_and_the_others_their_band(loaded_model) -> None:  # type: ignore[no-untyped-def]
    parts = ServiceCore(core_config(Settings()), model=loaded_model)._p
    mask = np.array([True, False, False, False, True, False, False])
    rel = parts.h_rel_for(H, BAND, mask)
    band = math.sqrt(0.1**2 + H_FORM_SD_LN**2 + H_NO_BASELINE_SD_LN**2)  # no baseline yet
    np.testing.assert_allclose(rel, np.where(mask, GUESSED_H_REL, band), rtol=1e-6)
    np.testing.assert_allclose(parts.h_rel_for(H, BAND), band, rtol=1e-6)  # no mask: the band alone


def test_a_served_fit_with_an_h_on_its_bound_gives_the_live_state_the_guessed_error(loaded_model) -> None:  # type: ignore[no-untyped-def]
    parts = ServiceCore(core_config(Settings()), model=loaded_model)._p
    parts.serve((_record(COND, at_bound=[True, False, False, False, False, False, False]), None))
    considered = np.array(parts.live._noise.h_rel)  # what the filter's cross-covariance is scaled by
    assert considered[0] == GUESSED_H_REL
    band = math.sqrt(0.1**2 + H_FORM_SD_LN**2 + H_NO_BASELINE_SD_LN**2)
    np.testing.assert_allclose(considered[1:], band, rtol=1e-6)


def test_a_restart_gives_the_stored_fits_h_on_its_bound_the_guessed_error(loaded_model) -> None:  # type: ignore[no-untyped-def]
    """The restore path as the served one: a stored H on its bound is a guess, the others carry their band
    with the form term and no baseline yet (set before a checkpoint resumes; nothing followed yet)."""
    rec = _record(COND, at_bound=[True, False, False, False, False, False, False])
    core = ServiceCore(core_config(Settings()), model=loaded_model, restored=Restored(last=rec))
    considered = np.array(core._p.live._noise.h_rel)
    assert considered[0] == GUESSED_H_REL
    band = math.sqrt(0.1**2 + H_FORM_SD_LN**2 + H_NO_BASELINE_SD_LN**2)  # as a served fit's
    np.testing.assert_allclose(considered[1:], band, rtol=1e-6)
