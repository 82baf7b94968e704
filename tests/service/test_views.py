"""The one mapping from an identification to what the API serves: ``data_to_record`` and ``chtc_snapshot``."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np

from api.schemas import chtc_out
from model.defaults import BOUND_REL_TOL
from model.hmap import Z95
from service.contracts.records import IdentificationData
from service.contracts.snapshots import ZONE_NAMES, ChtcSnapshot, ConditionSnapshot, ConditionState
from service.contracts.verdict import ChtcStatus, DataCode, DataProblem, Reason
from service.serve.policy import chtc_verdict
from service.serve.views import at_bound, chtc_snapshot, data_to_record, served_record

T = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
COND = ConditionSnapshot(
    id=7,
    speed_rpm=3000.0,
    torque_nm=5.0,
    ambient_c=22.0,
    since=T - timedelta(hours=1),
    state=ConditionState.STABLE,
)
H = [88.2, 46.3, 68.5, 46.7, 52.1, 70.2, 16.5]


def _data(**changes: Any) -> IdentificationData:
    data = IdentificationData(
        id=3,
        condition_id=COND.id,
        started_at=T,
        finished_at=T,
        window_start=T - timedelta(minutes=40),
        window_end=T,
        reason="scheduled",
        outcome="ok",
        method="hybrid",
        model_version="m",
        h=H,
        ci95_lo=[0.9 * x for x in H],
        ci95_hi=[1.1 * x for x in H],
        identified=[True] * 7,
        f=0.0225,
        fit=1 / 1.0225,
        rmse_c=0.15,
        diagnostics={"at_bound": [False] * 7},
    )
    return replace(data, **changes)


def _snap(
    data: IdentificationData,
    *,
    newest_sample_at: datetime | None = T,
    condition: ConditionSnapshot = COND,
    problems: tuple[DataProblem, ...] = (),
    restored: bool = False,
    box: tuple[float, float] | None = (5.0, 200.0),
) -> ChtcSnapshot:
    """The snapshot the shell builds: the record, and the policy's verdict on it (``chtc_verdict``)."""
    rec = data_to_record(data, COND)
    bound = at_bound(rec, box, BOUND_REL_TOL)
    verdict = chtc_verdict(
        has_sample=newest_sample_at is not None,
        problems=problems,
        live=None,
        now=T,
        condition=condition,
        record_condition_id=rec.condition.id,
        map_verdict=None,
        running=False,
        bound=[bool(b) for b in bound],
        identified=[bool(b) for b in rec.identified],
        prior_dominated=[bool(b) for b in rec.prior_dominated],
        h=[float(x) for x in rec.h],
        restored=restored,
        zones=ZONE_NAMES,
    )
    return chtc_snapshot(rec, newest_sample_at=newest_sample_at, verdict=verdict, bound=bound)


def test_the_record_is_the_stored_data_with_read_only_arrays() -> None:
    data = _data(h=[*H[:6], None], identified=[True] * 6 + [False])
    rec = data_to_record(data, COND)
    assert rec.data is data and rec.condition is COND
    assert np.isnan(rec.h[6]) and rec.h[0] == 88.2 and not rec.identified[6]
    assert (rec.window_from, rec.wall_s, rec.fit) == (data.window_start, data.duration_s, data.fit)
    assert not rec.h.flags.writeable and not rec.identified.flags.writeable


def test_a_value_the_identification_did_not_give_is_served_as_null() -> None:
    """The running service served a missing f as NaN and the in-memory one as 0.0; one builder, one answer."""
    snap = _snap(_data(f=None, fit=None, rmse_c=None))
    assert (snap.f, snap.fit, snap.rmse_c) == (None, None, None)
    body = chtc_out(snap, T, spindle_id="s1")
    assert (body.f_c2, body.fit, body.rmse_c) == (None, None, None)
    assert _snap(_data()).f == 0.0225


def test_an_h_on_the_search_box_bound_is_not_identified_and_not_usable() -> None:
    snap = _snap(_data(h=[*H[:6], 5.0]))  # H7 on the lower bound of the 5..200 box
    assert snap.at_bound.tolist() == [False] * 6 + [True]
    assert snap.identified.tolist() == [True] * 6 + [False]
    assert not snap.usable_for_compensation and snap.reason is not None
    assert snap.reason.startswith("at_bound: H7")
    flagged = _snap(_data(diagnostics={"at_bound": [True] + [False] * 6}), box=None)  # the fit's own flag
    assert flagged.at_bound.tolist() == [True] + [False] * 6


def test_usability_says_the_first_reason_in_order() -> None:
    assert _snap(_data()).usable_for_compensation and _snap(_data()).reason is None
    assert _snap(_data(), newest_sample_at=None).reason == "no_data: no sample acquired yet"
    stale = _snap(_data(), problems=(DataProblem(DataCode.DAQ_NO_GOOD_DATA, ""),), restored=True)
    assert stale.reason == "stale: daq_no_good_data (see /readyz)"
    assert stale.verdict.reason is Reason.STALE and stale.status is ChtcStatus.STALE
    moved = _snap(_data(), condition=replace(COND, id=8), restored=True)
    assert moved.reason == "condition_changed: identified at condition 7, now 8 (stable)"
    changing = replace(COND, state=ConditionState.CHANGING)
    assert _snap(_data(), condition=changing).reason == (
        "condition_changed: identified at condition 7, now 7 (changing)"
    )
    weak = _snap(_data(identified=[False, True, True, False, True, True, True]), restored=True)
    assert weak.reason == "not_identified: H1, H4 (95 % CI too wide, no prior holds it)"
    held = _snap(_data(identified=[False] * 7, diagnostics={"prior_dominated": [True] * 7}))
    assert held.usable_for_compensation  # a prior-dominated H has a finite, honest band: usable by a model
    restored = _snap(_data(), restored=True)
    assert not restored.usable_for_compensation
    assert restored.reason == "restored: the last stored H, not re-identified since the restart"


def test_the_served_band_carries_the_model_form_error_and_stays_in_the_search_box() -> None:
    # H7's fit band σ(ln H) 0.05 (narrow: flagged), H1's 0.24 (just identified), H2's the prior's ln 3
    sd = np.array([0.24, np.log(3.0), 0.1, 0.1, 0.1, 0.1, 0.05])
    h = np.array([150.0, 60.0, *H[2:]])
    z = Z95
    data = _data(h=list(h), ci95_lo=list(h * np.exp(-z * sd)), ci95_hi=list(h * np.exp(z * sd)))
    data = replace(data, identified=[True, False, True, True, True, True, True])
    rec = data_to_record(data, COND)
    served = served_record(rec, form_sd=0.15, ci_threshold=0.5, box=(5.0, 200.0))
    wide = np.sqrt(sd**2 + 0.15**2)
    np.testing.assert_allclose(served.ci95_lo[2:], h[2:] * np.exp(-z * wide[2:]), rtol=1e-9)
    np.testing.assert_allclose(served.ci95_hi[2:], h[2:] * np.exp(z * wide[2:]), rtol=1e-9)
    assert served.ci95_hi[0] == 200.0 and served.ci95_hi[1] == 200.0  # truncated to the box
    assert served.ci95_lo[1] == 60.0 * np.exp(-z * wide[1])
    # H1's band widened past the threshold: no longer identified; H2 never was
    assert served.identified.tolist() == [False, False, True, True, True, True, True]
    # nothing else changes, and without the form error and with a wide box the band is the fit's
    assert served.h is rec.h and served.id == rec.id
    same = served_record(rec, form_sd=0.0, ci_threshold=0.5, box=(0.0, np.inf))
    np.testing.assert_allclose(same.ci95_hi, rec.ci95_hi, rtol=1e-12)
    assert same.identified.tolist() == rec.identified.tolist()
