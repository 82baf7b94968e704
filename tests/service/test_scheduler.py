"""The identification scheduler driven with events only (no clock, no sleeps)."""

from __future__ import annotations

from dataclasses import replace

import pytest

from service.identify.detector import OperatingPoint
from service.identify.scheduler import (
    CancelJob,
    ConditionStarted,
    IdentificationScheduler,
    JobFailed,
    JobFinished,
    JobSkipped,
    ManualQueued,
    ManualRejected,
    ManualRequest,
    PastResult,
    SchedulerError,
    SchedulerStatus,
    StartJob,
    Tick,
)
from tests.engine_config import product_core

# the product's scheduler with 10-min windows at 10, 20, 40, 60 min (the paper's schedule: these tests' round
# times; the product's first window is 7 min)
CFG = product_core(identification={"schedule_min": (10.0, 20.0, 40.0, 60.0), "min_window_s": 600.0}).scheduler
P3000 = OperatingPoint(speed_rpm=3000, torque_nm=2.0, ambient_c=23.2)
P4000 = OperatingPoint(speed_rpm=4000, torque_nm=2.0, ambient_c=21.8)
P5000 = OperatingPoint(speed_rpm=5000, torque_nm=2.0, ambient_c=22.0)
H_A = (88.0, 46.0, 68.0, 47.0, 52.0, 70.0, 16.0)
H_B = (80.0, 46.0, 62.0, 45.0, 46.0, 68.0, 11.0)


def ticks(s: IdentificationScheduler, t_from: float, t_to: float, dt: float = 10.0) -> list:
    out = []
    t = t_from
    while t <= t_to:
        out += s.handle(Tick(t))
        t += dt
    return out


def test_first_request_after_min_data_then_schedule():
    s = IdentificationScheduler(config=CFG)
    assert s.status is SchedulerStatus.IDLE
    assert s.handle(ConditionStarted(t=60, condition_id=1, point=P3000, t_start=0)) == []
    assert s.status is SchedulerStatus.COLLECTING
    assert ticks(s, 70, 590) == []
    (job,) = s.handle(Tick(600))
    assert isinstance(job, StartJob) and job.t_from == 0 and job.t_to == 600
    assert job.warm_start is None and job.warm_source == "none" and job.trigger == "schedule"
    assert s.status is SchedulerStatus.RUNNING
    assert ticks(s, 610, 700) == []  # one job at a time
    assert s.handle(JobFinished(t=700, job_id=job.job_id, h=H_A)) == []
    assert s.status is SchedulerStatus.WAITING
    starts = []
    for t in range(710, 5000, 10):
        out = s.handle(Tick(t))
        for ins in out:
            assert isinstance(ins, StartJob)
            starts.append(ins)
            s.handle(JobFinished(t=t, job_id=ins.job_id, h=H_A))
    assert [j.t_to for j in starts] == [1200, 2400, 3600]
    assert all(j.warm_start == H_A and j.warm_source == "this condition" for j in starts)
    assert starts[-1].t_from == 0  # max_window_s caps at 3600 s: window [0, 3600]
    assert s.status is SchedulerStatus.DONE


def test_window_is_capped_at_max_window():
    cfg = replace(CFG, schedule_s=(600.0, 4000.0), max_window_s=1800.0)
    s = IdentificationScheduler(config=cfg)
    s.handle(ConditionStarted(t=60, condition_id=1, point=P3000, t_start=0))
    (j1,) = s.handle(Tick(600))
    s.handle(JobFinished(t=610, job_id=j1.job_id, h=H_A))
    (j2,) = s.handle(Tick(4000))
    assert (j2.t_from, j2.t_to) == (4000 - 1800, 4000)


def test_due_entry_while_running_starts_on_finish_and_merges_missed():
    s = IdentificationScheduler(config=CFG)
    s.handle(ConditionStarted(t=60, condition_id=1, point=P3000, t_start=0))
    (j1,) = s.handle(Tick(600))
    assert ticks(s, 610, 2500) == []  # 1200 and 2400 fall due while j1 runs
    (j2,) = s.handle(JobFinished(t=2500, job_id=j1.job_id, h=H_A))
    assert j2.t_to == 2500 and j2.warm_start == H_A
    s.handle(JobFinished(t=2510, job_id=j2.job_id, h=H_B))
    (j3,) = ticks(s, 2520, 3600)
    assert j3.t_to == 3600 and j3.warm_start == H_B  # only the 3600 s entry is left


def test_new_condition_cancels_running_job_and_warm_starts_from_nearest():
    s = IdentificationScheduler(config=CFG)
    s.handle(ConditionStarted(t=60, condition_id=1, point=P3000, t_start=0))
    (j1,) = s.handle(Tick(600))
    s.handle(JobFinished(t=650, job_id=j1.job_id, h=H_A))
    (j2,) = s.handle(Tick(1200))
    out = s.handle(ConditionStarted(t=1300, condition_id=2, point=P4000, t_start=1240))
    assert out == [CancelJob(j2.job_id, "superseded by condition 2")]
    assert s.status is SchedulerStatus.COLLECTING
    assert s.handle(JobFinished(t=1310, job_id=j2.job_id, h=H_B)) == []  # late result of a cancelled job
    (j3,) = ticks(s, 1310, 1840)
    assert j3.condition_id == 2 and j3.t_from == 1240 and j3.t_to == 1840
    assert j3.warm_start == H_A and j3.warm_source == "condition 1"


def test_nearest_earlier_condition_is_chosen_by_distance():
    history = [
        PastResult(condition_id=1, point=P3000, h=H_A),
        PastResult(condition_id=2, point=P5000, h=H_B),
    ]
    s = IdentificationScheduler(config=CFG, history=list(history))
    s.handle(
        ConditionStarted(
            t=0,
            condition_id=3,
            point=OperatingPoint(speed_rpm=4800, torque_nm=2.0, ambient_c=22.0),
            t_start=0,
        )
    )
    (job,) = ticks(s, 10, 600)
    assert job.warm_start == H_B and job.warm_source == "condition 2"
    # a restored condition warm-starts from its own stored result
    s2 = IdentificationScheduler(config=CFG, history=list(history))
    s2.handle(ConditionStarted(t=0, condition_id=1, point=P3000, t_start=0))
    (job2,) = ticks(s2, 10, 600)
    assert job2.warm_start == H_A and job2.warm_source == "this condition"


def test_skipped_and_failed_jobs_wait_for_next_entry():
    s = IdentificationScheduler(config=CFG)
    s.handle(ConditionStarted(t=0, condition_id=1, point=P3000, t_start=0))
    (j1,) = s.handle(Tick(600))
    assert s.handle(JobSkipped(t=610, job_id=j1.job_id, reason="too little good data")) == []
    assert s.status is SchedulerStatus.COLLECTING
    (j2,) = ticks(s, 620, 1200)
    assert j2.t_to == 1200 and j2.warm_start is None
    assert s.handle(JobFailed(t=1210, job_id=j2.job_id, reason="boom")) == []
    assert s.status is SchedulerStatus.COLLECTING  # still no result of this condition
    (j3,) = ticks(s, 1220, 2400)
    assert j3.warm_start is None


def test_manual_requests():
    s = IdentificationScheduler(config=CFG)
    (r,) = s.handle(ManualRequest(t=0))
    assert isinstance(r, ManualRejected) and "no operating condition" in r.reason
    s.handle(ConditionStarted(t=0, condition_id=1, point=P3000, t_start=0))
    (r,) = s.handle(ManualRequest(t=100))
    assert isinstance(r, ManualRejected) and "min_data_s" in r.reason
    (j1,) = s.handle(ManualRequest(t=700))
    assert isinstance(j1, StartJob) and j1.trigger == "manual" and j1.t_to == 700
    (q,) = s.handle(ManualRequest(t=710))
    assert isinstance(q, ManualQueued)
    (j2,) = s.handle(JobFinished(t=720, job_id=j1.job_id, h=H_A))
    assert j2.trigger == "manual" and j2.warm_start == H_A and j2.t_to == 720
    s.handle(JobFinished(t=730, job_id=j2.job_id, h=H_A))
    (j3,) = ticks(s, 740, 1200)  # the manual runs consumed the 600 s entry only
    assert j3.t_to == 1200 and j3.trigger == "schedule"


def test_bad_config_and_event():
    with pytest.raises(SchedulerError, match="schedule_s"):
        replace(CFG, schedule_s=(300.0, 1200.0))
    with pytest.raises(SchedulerError, match="schedule_s"):
        replace(CFG, schedule_s=(1200.0, 600.0))
    with pytest.raises(SchedulerError, match="max_window_s"):
        replace(CFG, max_window_s=100.0)
    with pytest.raises(SchedulerError, match="unknown"):
        IdentificationScheduler(config=CFG).handle("tick")  # type: ignore[arg-type]
