"""Ring-buffer samples -> uniform identification window: mask, hole filling, insufficient data."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.identify.window import InsufficientWindowError, RawWindow, resample_window
from tests.engine_config import product_core

# the product's rules (10-s grid, 24 good channels) with a 10-min minimum window and stricter hole rules than
# the product's (0.8, 300 s), so the short synthetic windows below reach each rule's edge
RULES = replace(product_core().rules, min_window_s=600.0, min_good_fraction=0.9, max_gap_s=60.0)


def raw(n: int = 121, *, jitter: float = 0.0, seed: int = 0) -> RawWindow:
    rng = np.random.default_rng(seed)
    t = 1000.0 + 10.0 * np.arange(n) + rng.uniform(-jitter, jitter, n)
    temps = 20.0 + 0.01 * (t - 1000.0)[:, None] + np.arange(32)[None, :]
    return RawWindow(
        times_s=t,
        temps_c=temps,
        quality=np.zeros((n, 32), dtype=np.uint8),
        ambient_c=np.full(n, 22.0),
        speed_rpm=np.full(n, 3000.0),
        torque_nm=np.full(n, 2.0),
    )


def test_clean_window_with_jitter_is_resampled_exactly():
    r = raw(jitter=3.0)
    w = resample_window(r, 1000.0, 2200.0, RULES)
    assert w.n_steps == 120 and w.dt_s == 10.0
    assert w.mask.all()
    # each grid point took the nearest sample: values equal the samples', which are at most 3 s off
    assert (
        np.max(np.abs(w.measured_c - (20.0 + 0.01 * (w.times_s - 1000.0))[:, None] - np.arange(32))) <= 0.031
    )
    amb, speed, _ = w.step_inputs()
    assert amb.shape == (120,) and np.all(speed == 3000.0)


def test_bad_channels_are_masked_and_short_holes_filled():
    r = raw()
    q = r.quality.copy()
    q[:, 4] = 2  # open circuit all along
    q[50:60, 7] = 5  # 100 s stuck: longer than max_gap_s 60 s
    q[30:32, 9] = 1  # a 20 s hole: filled
    temps = r.temps_c.copy()
    temps[30:32, 9] = 999.0
    r2 = replace(r, temps_c=temps, quality=q)
    w = resample_window(r2, 1000.0, 2200.0, RULES)
    assert not w.mask[4] and not w.mask[7] and w.mask[9]
    assert w.mask.sum() == 30
    np.testing.assert_allclose(w.measured_c[30:32, 9], 20.0 + 0.01 * w.times_s[30:32] - 10.0 + 9.0)


def test_too_few_good_channels_is_insufficient_with_reason():
    r = raw()
    q = r.quality.copy()
    q[:, :10] = 2
    r2 = replace(r, quality=q)
    with pytest.raises(
        InsufficientWindowError, match=r"only 22 channels .*min_good_channels=24.*ch1 \(0 % ok\)"
    ):
        resample_window(r2, 1000.0, 2200.0, RULES)


def test_short_window_and_missing_can_are_insufficient():
    with pytest.raises(InsufficientWindowError, match="shorter than min_window_s"):
        resample_window(raw(), 1000.0, 1500.0, RULES)
    r = raw()
    speed = r.speed_rpm.copy()
    speed[:40] = np.nan
    r2 = replace(r, speed_rpm=speed)
    with pytest.raises(InsufficientWindowError, match="speed_rpm was missing on 33 %"):
        resample_window(r2, 1000.0, 2200.0, RULES)


def test_samples_missing_in_time_count_as_bad():
    r = raw()
    keep = np.ones(len(r.times_s), dtype=bool)
    keep[20:40] = False  # 200 s with no sample at all
    names = ("times_s", "temps_c", "quality", "ambient_c", "speed_rpm", "torque_nm")
    r2 = RawWindow(**{n: getattr(r, n)[keep] for n in names})
    with pytest.raises(InsufficientWindowError, match="ambient_c was missing on 17 %"):
        resample_window(r2, 1000.0, 2200.0, RULES)
    with pytest.raises(InsufficientWindowError, match="no samples"):
        resample_window(r, 5000.0, 6000.0, RULES)


def test_a_daq_silent_at_the_end_ends_the_window_at_its_last_good_point():
    # the acquisition's stale samples (DAQ down, CAN alive): the last temperatures repeated, quality stale
    r = raw()
    q, temps = r.quality.copy(), r.temps_c.copy()
    q[100:] = 1
    temps[100:] = temps[99]
    w = resample_window(replace(r, temps_c=temps, quality=q), 1000.0, 2200.0, RULES)
    assert w.n_steps == 99 and w.times_s[-1] == 1990.0
    assert w.mask.all()  # no channel lost: nothing was held over the outage
    np.testing.assert_allclose(w.measured_c, r.temps_c[:100])


def test_a_daq_silent_for_most_of_the_window_is_insufficient_and_says_since_when():
    r = raw()
    q = r.quality.copy()
    q[40:] = 1
    with pytest.raises(InsufficientWindowError, match=r"no usable temperature since t=1390 s: 390 s of data"):
        resample_window(replace(r, quality=q), 1000.0, 2200.0, RULES)
