"""The core builds the right identification window from the ring buffer, skips with a reason when the data
are too poor, and the worker process runs (and cancels) identifications."""

from __future__ import annotations

import asyncio
import dataclasses
from datetime import timedelta

import numpy as np
import pytest

from model.plant import ChannelFault, Segment
from service.core.events import Log, ManualRequested, Rejected, RejectKind
from service.core.machine import ServiceCore
from service.identify.worker import (
    IdentificationWorker,
    JobStatus,
    final_field,
    run_identification,
)
from tests.engine_config import PER_CONDITION_10_20, product_core

from .conftest import T0, plant_run, samples_of
from .drive import feed, launches, stored

# the product's defaults but the per-condition protocol with 10-min windows (PER_CONDITION_10_20: these tests'
# timings)
CFG = product_core(identification=PER_CONDITION_10_20)


def test_window_of_the_first_launch(loaded_model):
    """5 min idle (the filtered state converges at rest), then 3000 rpm: the first launch is the 3000 rpm
    condition's 10-min window, starting from the filtered state there with its covariance."""
    run = plant_run([Segment(300.0, 0.0, 0.0, 23.2), Segment(900.0, 3000.0, 2.0, 23.2)])
    core = ServiceCore(CFG, model=loaded_model)
    out = feed(core, samples_of(run))
    assert len(launches(out)) == 1  # the 1200 s entry is not due within 900 s
    (launch,) = launches(out)
    w = launch.request.window
    start = round(float(w.times_s[0] - T0) / 10.0)
    assert abs(w.times_s[0] - (T0 + 300.0)) <= 10.0 and w.times_s[-1] - w.times_s[0] == pytest.approx(600.0)
    assert launch.request.warm_start is None
    (said,) = [i.message for i in out if isinstance(i, Log) and i.event_id == launch.event_id]
    assert said.startswith(f"identification {launch.job_key}:") and said.endswith("warm start from none")
    assert w.n_steps == 60 and w.dt_s == 10.0 and w.mask.all()
    np.testing.assert_allclose(w.measured_c, run.temps_c[start : start + 61])
    _, speed, _ = w.step_inputs()
    assert np.all(speed[1:] == 3000.0)
    # the initial field is the filtered state at the window start: at the sensors within its noise of the
    # measured temperatures, with its covariance as the start uncertainty
    at_sensors = loaded_model.fe.sensor_op @ np.asarray(launch.request.t0_c)
    assert np.max(np.abs(at_sensors - run.temps_c[start])) < 0.6
    r = loaded_model.rom.rank
    assert launch.request.start_cov is not None and launch.request.start_cov.shape == (r, r)
    assert launch.request.start_modes == CFG.start_modes
    assert core.view().jobs[launch.job_key].state.value == "running"


def test_too_few_good_channels_is_skipped_with_reason(loaded_model):
    faults = [ChannelFault(channel=c, kind="open", start_s=100.0) for c in range(1, 11)]
    run = plant_run([Segment(1900.0, 3000.0, 2.0, 23.2)], faults=faults)
    core = ServiceCore(CFG, model=loaded_model)
    out = feed(core, samples_of(run))
    assert launches(out) == []
    view = core.view()
    skipped = [r for r in view.records if r.outcome == "insufficient-data"]
    assert len(skipped) == 2  # the 600 s and the 1200 s entries, counted from the live state's convergence
    assert "only 22 channels" in skipped[0].message and "ch1 (" in skipped[0].message
    idents = [r for r in stored(out) if type(r).__name__ == "IdentificationData"]
    assert [r.outcome for r in idents] == ["insufficient-data", "insufficient-data"]
    assert view.counts["insufficient-data"] == 2
    samples = [r for r in stored(out) if type(r).__name__ == "SampleData"]
    assert samples[-1].quality[0] == "open_circuit" and samples[-1].quality[20] == "ok"


def test_jittered_samples_are_all_stored(loaded_model):
    """Issue 13.6: stamps jittered around the 10 s period: one stored row per sample, none dropped."""
    run = plant_run([Segment(600.0, 3000.0, 2.0, 23.2)])
    rng = np.random.default_rng(3)
    samples = [
        dataclasses.replace(s, t=s.t + timedelta(seconds=float(rng.uniform(-2.0, 2.0))))
        for s in samples_of(run)
    ]
    core = ServiceCore(CFG, model=loaded_model)
    out = feed(core, samples)
    kept = [r.t for r in stored(out) if type(r).__name__ == "SampleData"]
    assert kept == [s.t for s in samples]


@pytest.fixture(scope="module")
def window_request(loaded_model):
    run = plant_run([Segment(1800.0, 3000.0, 2.0, 23.2)])
    core = ServiceCore(CFG, model=loaded_model)
    (launch,) = launches(feed(core, samples_of(run)))
    return launch.request


def test_start_offset_is_fitted_and_carried_into_the_final_field(loaded_model, window_request):
    """A live state 0.3 °C too warm: the fit finds −0.3 °C, and the field the live state is rebased on
    starts from the corrected field (its end differs from the uncorrected one by a decayed −0.3 °C)."""
    warm = dataclasses.replace(
        window_request, t0_c=np.asarray(window_request.t0_c) + 0.3, estimate_t0_shift=True
    )
    result, window = run_identification(loaded_model, warm)
    assert result.t0_shift_c is not None and abs(result.t0_shift_c + 0.3) < 0.05, result.t0_shift_c
    assert warm.carry_start_error and result.end_ensemble is not None  # the default: the end state is reused
    corrected = final_field(loaded_model, window, result)
    recomputed = final_field(loaded_model, window, dataclasses.replace(result, end_ensemble=None))
    np.testing.assert_allclose(corrected, recomputed, atol=1e-6)
    uncorrected = final_field(
        loaded_model, window, dataclasses.replace(result, t0_shift_c=None, end_ensemble=None)
    )
    diff = corrected - uncorrected
    assert np.all(diff < 0.0) and np.all(diff > -0.3), (diff.min(), diff.max())


def test_worker_process_runs_and_cancels(model_ref, window_request, loaded_model):
    async def scenario():
        worker = IdentificationWorker(model_ref, timeout_s=120.0)
        try:
            version = await worker.start()
            ok = await worker.run(window_request)
            worker_cancel = dataclasses.replace(window_request, job_id=99, warm_start=None)
            task = asyncio.ensure_future(worker.run(worker_cancel))
            worker.cancel(99)
            cancelled = await task
            return version, ok, cancelled
        finally:
            worker.close()

    version, ok, cancelled = asyncio.run(scenario())
    assert version == loaded_model.version
    assert ok.status is JobStatus.OK, ok.message
    assert ok.result.fit > 0.9 and ok.final_field_c.shape == (loaded_model.fe.n_nodes,)
    assert cancelled.status is JobStatus.CANCELLED


def _manual(core: ServiceCore, n: int, reason: str = "manual") -> list:
    return core.handle(ManualRequested(f"manual-{n}", reason))


def test_manual_requests_and_idle_condition(loaded_model):
    run = plant_run([Segment(1000.0, 0.0, 0.0, 22.0), Segment(700.0, 3000.0, 5.0, 22.0)])
    core = ServiceCore(CFG, model=loaded_model)
    assert _manual(core, 1) == [
        Rejected(
            event_id="manual-1",
            kind=RejectKind.NOT_READY,
            reason="no samples yet: nothing to identify from",
        )
    ]
    samples = samples_of(run)
    # the idle condition: the live state converges (~5 min), its job 10 min later is skipped
    feed(core, samples[:101])
    (idle,) = [r for r in core.view().records if r.outcome == "skipped"]
    assert "idle" in idle.message and "not identifiable" in idle.message
    assert launches(feed(core, samples[101:130], first=102)) == []  # ~4 min of the 3000 rpm condition
    (refused,) = _manual(core, 2)
    assert isinstance(refused, Rejected) and refused.kind is RejectKind.NOT_READY
    assert "min_data_s" in refused.reason
    started = launches(feed(core, samples[130:], first=131))
    assert len(started) == 1 and started[0].request.window.step_inputs()[1][0] == pytest.approx(
        3000.0, rel=0.05
    )
    (busy,) = _manual(core, 3)
    assert isinstance(busy, Rejected) and busy.kind is RejectKind.BUSY and "already running" in busy.reason


def test_chained_windows_carry_the_start_field_error(loaded_model):
    """With ``carry_start_error`` (and no start directions fitted) the windows carry the filtered state's
    covariance at their start: the CIs widen, the H stay (nearly: the filter weighs later H by their CIs)."""
    from service.core.offline import run_offline

    run = plant_run([Segment(1300.0, 3000.0, 2.0, 23.2), Segment(1300.0, 4000.0, 3.0, 23.2)])
    samples = samples_of(run)
    # calibration off: this profile never rests, and the no-baseline offset uncertainty (0.17 °C per
    # channel, service.acquire.calibration) would dominate every CI width and hide the start-field term
    base = dataclasses.replace(CFG, carry_start_error=False, calibration=None, start_modes=0)
    off, on = (
        [r for r in run_offline(samples, model=loaded_model, config=cfg).records if r.outcome == "ok"]
        for cfg in (base, dataclasses.replace(base, carry_start_error=True))
    )
    assert len(on) == len(off) >= 3  # the first window waits for the filter's convergence
    width = lambda rec: np.asarray(rec.ci95_hi) - np.asarray(rec.ci95_lo)  # noqa: E731
    # the first window starts from the same filtered state: same H, wider CIs
    np.testing.assert_allclose(on[0].h, off[0].h, rtol=1e-9)
    assert np.all(width(on[0]) >= width(off[0]) * (1 - 1e-9)) and np.any(width(on[0]) > 1.05 * width(off[0]))
    # later ones start from states that the (differently wide) earlier CIs weighted: H within a small part
    # of the CI
    for a, b in zip(off[1:], on[1:], strict=True):
        assert np.all(np.abs(b.h - a.h) <= 0.25 * width(a)), (a.h, b.h)
        assert np.median(width(b) / width(a)) > 1.0


def test_one_mapping_from_a_job_failure_to_its_stored_outcome(loaded_model, window_request):
    """``run_job`` (the worker process's function, also run offline) never raises: too few usable data,
    whether the window rules or the identification itself find it, is "insufficient-data" with the reason;
    a cancelled job "cancelled"; anything else "failed", naming the error."""
    from service.contracts.outcome import Outcome
    from service.estimate.live import LiveStateError
    from service.identify.window import InsufficientWindowError
    from service.identify.worker import JobCancelled, job_outcome_of, run_job

    blind = dataclasses.replace(window_request.window, mask=np.zeros(32, dtype=bool))
    out = run_job(loaded_model, dataclasses.replace(window_request, window=blind))
    assert out.status is Outcome.INSUFFICIENT_DATA and "channels" in out.message, out.message
    assert out.result is None and out.final_field_c is None
    bad_t0 = dataclasses.replace(window_request, t0_c=np.zeros(3))
    out = run_job(loaded_model, bad_t0)
    assert out.status is Outcome.FAILED and out.message.startswith("IdentificationError: window.t0")
    out = run_job(None, window_request)
    assert (out.status, out.message) == (
        Outcome.FAILED,
        "RuntimeError: worker process has no model (initializer failed)",
    )
    assert job_outcome_of(InsufficientWindowError("only 3 channels")) == (
        Outcome.INSUFFICIENT_DATA,
        "only 3 channels",
    )
    assert job_outcome_of(LiveStateError("no snapshot at t=5 s")) == (
        Outcome.INSUFFICIENT_DATA,
        "no snapshot at t=5 s",
    )
    assert job_outcome_of(JobCancelled()) == (Outcome.CANCELLED, "cancelled")
