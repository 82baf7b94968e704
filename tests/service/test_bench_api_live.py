"""``python -m benchmarks api``'s live bench (issue 30): its pure helpers, and the CPU hog it starts and
kills."""

from __future__ import annotations

import argparse

import pytest

from benchmarks.api_live import (
    add_arguments,
    classify,
    cpu_hog,
    lag_max_bound_s,
    process_cpu_s,
    rig_pids,
)


def test_requests_are_classed_by_the_last_poll_before_them() -> None:
    marks = [(1.0, False), (2.0, True), (3.0, False)]
    sent = [0.5, 1.5, 2.1, 2.9, 3.5]
    lat = [0.10, 0.11, 0.20, 0.21, 0.12]
    busy, idle = classify(sent, lat, marks)
    assert busy == [0.20, 0.21]
    assert idle == [0.10, 0.11, 0.12]  # before the first poll: not known to be identifying


def test_loop_lag_max_is_the_highest_bucket_observed_between_scrapes() -> None:
    # cumulative buckets (s -> count): between the scrapes 10 lags <= 1 ms, 3 in (1, 10] ms, 1 in (10, 50] ms
    before = {0.001: 10.0, 0.01: 12.0, 0.05: 12.0, 0.1: 13.0}
    after = {0.001: 20.0, 0.01: 25.0, 0.05: 26.0, 0.1: 27.0}
    assert lag_max_bound_s(before, after) == pytest.approx(0.05)
    later = {0.001: 20.0, 0.01: 25.0, 0.05: 26.0, 0.1: 28.0}  # one more in (50, 100] ms
    assert lag_max_bound_s(after, later) == pytest.approx(0.1)
    assert lag_max_bound_s(before, before) == 0.0


def test_cpu_hog_runs_one_busy_process_each_and_kills_them() -> None:
    with cpu_hog(2) as procs:
        assert len(procs) == 2 and all(p.is_alive() for p in procs)
        pids = [p.pid for p in procs]
        assert all(pid is not None for pid in pids)
    assert not any(p.is_alive() for p in procs)


def test_process_cpu_reads_proc() -> None:
    import os

    assert process_cpu_s(os.getpid()) > 0.0


def test_the_rig_process_is_told_apart_by_its_name() -> None:
    """The bench reports the service's CPU without the demo's rig: the child named ``chtc-rig``."""
    import os
    import subprocess
    import sys

    other = "print(1, flush=True); input()"
    code = "from simulator.rigproc import name_process; name_process('chtc-rig'); " + other
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    procs = [
        subprocess.Popen([sys.executable, "-c", c], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        for c in (code, other)
    ]
    try:
        for p in procs:
            assert p.stdout is not None and p.stdout.readline()  # named (or not) by now
        assert rig_pids(os.getpid()) == [procs[0].pid]
    finally:
        for p in procs:
            p.kill()
            p.wait()


def test_short_mode_and_runs_are_options() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--short", "--speedups", "1,60"])
    assert args.short and args.speedups == "1,60"
