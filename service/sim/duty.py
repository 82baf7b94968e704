"""Seeded machining duty cycles for the virtual plant (``chtc bench duty``, the map-mode tests).

A duty cycle: ``idle_s`` at rest (the offset baseline's rest), then until ``duration_s`` the speed changes
every 1–6 min (whole minutes) among 0, 500, …, 7000 rpm (never the same twice in a row), torque 3–15 N·m (0 at
rest), the ambient drifting within ±1 °C around ``ambient_c`` (a sinusoid of random phase and a 2–4 h
period, held per segment, as the plant takes one ambient per segment). Issue 17's measured case.
"""

from __future__ import annotations

import numpy as np

from model.plant import Segment

__all__ = ["SPEEDS_RPM", "condition_at", "duty_profile"]

SPEEDS_RPM = tuple(float(n) for n in range(0, 7001, 500))


def duty_profile(
    seed: int, *, duration_s: float, idle_s: float = 300.0, ambient_c: float = 22.0
) -> list[Segment]:
    """The seeded duty cycle (module docstring) as plant segments; ``duration_s`` includes ``idle_s``."""
    if not (duration_s > idle_s >= 0):
        raise ValueError(f"duration_s: must be > idle_s ({idle_s} s), got {duration_s}")
    rng = np.random.default_rng(seed)
    phase, period_s = rng.uniform(0, 2 * np.pi), rng.uniform(2.0, 4.0) * 3600.0
    speeds = np.array(SPEEDS_RPM)

    def ambient(t: float) -> float:
        return round(float(ambient_c + np.sin(phase + 2 * np.pi * t / period_s)), 2)

    out = [Segment(idle_s, 0.0, 0.0, ambient(0.0))] if idle_s > 0 else []
    t, last = idle_s, 0.0
    while t < duration_s - 1e-9:
        dur = min(60.0 * int(rng.integers(1, 7)), duration_s - t)
        speed = float(rng.choice(speeds[speeds != last]))
        torque = 0.0 if speed == 0 else round(float(rng.uniform(3.0, 15.0)), 2)
        out.append(Segment(dur, speed, torque, ambient(t + 0.5 * dur)))
        t, last = t + dur, speed
    return out


def condition_at(profile: list[Segment], t_s: float) -> Segment:
    """The segment running at plant time ``t_s`` (s from the profile's start; a step k → k+1 uses the
    segment at k's time, as the plant's zero-order hold)."""
    end = 0.0
    for seg in profile:
        end += seg.duration_s
        if t_s < end - 1e-9:
            return seg
    return profile[-1]
