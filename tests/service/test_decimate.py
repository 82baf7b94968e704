"""The sample decimator keeps one sample per grid slot of ``sample_store_period_s``, whatever the jitter.

docs/design/persistence.md: "samples grow by about 8640 rows per day at the default period" (10 s).
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from service.acquire.decimate import SampleDecimator

T0 = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
DAY_S = 86_400.0


def kept_per_day(stamps_s: np.ndarray, period_s: float = 10.0) -> int:
    dec = SampleDecimator(period_s)
    return sum(dec.keep(T0 + timedelta(seconds=float(s))) for s in stamps_s)


def test_grid_slots_and_clock_step_back() -> None:
    dec = SampleDecimator(10.0)
    # slots (nearest multiple of 10 s): 0, 0, 1, 1, 1, 3, 3, 4, then 1 (clock stepped back), 1
    offsets = [0.0, 1.0, 9.99, 10.0, 12.0, 25.0, 34.9, 35.0, 5.0, 6.0]
    kept = [o for o in offsets if dec.keep(T0 + timedelta(seconds=o))]
    assert kept == [0.0, 9.99, 25.0, 35.0, 5.0]
    with pytest.raises(ValueError, match="sample_store_period_s"):
        SampleDecimator(0.0)


@pytest.mark.parametrize("jitter_s", [0.0, 0.5, 2.0, 4.0])
def test_jittered_10_s_acquisition_stores_8640_rows_per_day(jitter_s: float) -> None:
    rng = np.random.default_rng(7)
    grid = np.arange(0.0, DAY_S, 10.0)
    stamps = grid + rng.uniform(-jitter_s, jitter_s, grid.size)
    assert kept_per_day(stamps) == 8640


def test_faster_jittered_acquisition_stores_one_row_per_period() -> None:
    rng = np.random.default_rng(8)
    grid = np.arange(0.0, DAY_S, 1.0)  # 1 s acquisition stored every 10 s
    stamps = grid + rng.uniform(-0.3, 0.3, grid.size)
    n = kept_per_day(stamps)
    assert n in (8640, 8641)  # the first slot may be a half slot
    dec = SampleDecimator(10.0)
    kept = np.array([s for s in stamps if dec.keep(T0 + timedelta(seconds=float(s)))])
    gaps = np.diff(kept)
    # a kept stamp lies in [10k - 5, 10k - 4 + 0.3]: gaps at most period + acquisition period + 2 x jitter
    assert gaps.mean() == pytest.approx(10.0, abs=0.01) and gaps.max() <= 11.6
