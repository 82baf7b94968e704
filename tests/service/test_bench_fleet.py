"""``python -m benchmarks fleet``'s parts: the quantile of a scraped histogram (pure), and one short real run
of two hosted spindles (devices process, ``chtc run`` with ``[[spindles]]``, PostgreSQL) whose figures come
out measured, not made up. Slow: about half a minute."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.fleet_host import p99_of, run_n, write_buckets

INF = float("inf")


def test_the_quantile_interpolates_inside_its_bucket_over_the_window_only() -> None:
    before = {0.01: 100.0, 0.05: 100.0, INF: 100.0}  # 100 fast writes before the window
    after = {0.01: 150.0, 0.05: 199.0, INF: 200.0}  # then 50 ≤ 10 ms, 49 in (10, 50] ms, 1 slower
    q = p99_of(before, after)
    assert q is not None
    assert 0.049 < q <= 0.05  # rank 99 of 100: the last of the (10, 50] bucket
    assert p99_of(after, after) is None  # nothing written in the window
    assert p99_of({}, {0.01: 10.0, INF: 10.0}) == pytest.approx(0.0099)


def test_the_write_histogram_is_summed_over_the_spindles() -> None:
    text = "\n".join(
        [
            "# TYPE chtc_db_write_seconds histogram",
            'chtc_db_write_seconds_bucket{le="0.01",spindle="a"} 3.0',
            'chtc_db_write_seconds_bucket{le="+Inf",spindle="a"} 4.0',
            'chtc_db_write_seconds_bucket{le="0.01",spindle="b"} 1.0',
            'chtc_db_write_seconds_bucket{le="+Inf",spindle="b"} 2.0',
            'chtc_db_write_seconds_count{spindle="a"} 4.0',
        ]
    )
    assert write_buckets(text) == {0.01: 4.0, INF: 6.0}


@pytest.mark.slow
@pytest.mark.postgres
def test_a_short_fleet_run_measures_two_hosted_spindles(pg_url: str, tmp_path: Path) -> None:
    row_bytes = {"samples": 300.0, "samples_1min": 330.0, "conditions": 550.0}
    r = run_n(2, pg_url=pg_url, warmup_s=3.0, window_s=15.0, plants=2, workdir=tmp_path, row_bytes=row_bytes)
    assert r["spindles"] == 2 and r["running"] == 2
    assert r["writes"] > 0 and r["write_p99_ms"] is not None and r["write_p99_ms"] > 0
    assert 0 < r["connections"] <= 2 * 15  # the shared engines' pools, not one pool per spindle
    assert r["cpu_pct"] > 0 and r["rss_main_mib"] > 100  # a loaded model lives in the main process
    assert r["pool_processes"] >= 1
    # samples every 10 s per spindle: about 8640 a spindle-day, from the rows the database gained
    assert 4000 < r["rows_per_spindle_day"]["samples"] < 20000, r["rows_per_spindle_day"]
    assert r["bytes_per_spindle_day"] > 0
