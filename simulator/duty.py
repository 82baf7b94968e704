"""Seeded machining duty cycles for the virtual plant (``python -m benchmarks duty``, the map-mode tests).

A duty cycle: ``idle_s`` at rest (the offset baseline's rest), then until ``duration_s`` the speed changes
every 1–6 min (whole minutes) among 0, 500, …, 7000 rpm (never the same twice in a row), torque 3–15 N·m (0 at
rest), the ambient drifting within ±1 °C around ``ambient_c`` (a sinusoid of random phase and a 2–4 h
period, held per segment, as the plant takes one ambient per segment). Issue 17's measured case.

``duty_cycle(seed)`` yields the same kind of segments on and on (``chtc demo`` runs it until stopped).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from model.plant import Segment

__all__ = ["SPEEDS_RPM", "condition_at", "duty_cycle", "duty_profile"]

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


def duty_cycle(
    seed: int,
    *,
    idle_s: float = 300.0,
    ambient_c: float = 22.0,
    max_speed_rpm: float = 7000.0,
    torque_nm: tuple[float, float] = (3.0, 15.0),
    segment_s: float | None = None,
) -> Iterator[Segment]:
    """The seeded duty cycle without an end: ``idle_s`` at rest, then a new speed every 1–6 min (whole
    minutes; every ``segment_s`` s when given) among 0, 500, …, ``max_speed_rpm`` rpm (never the same twice
    in a row), torque uniform in ``torque_nm`` N·m (0 at rest), the ambient drifting as in
    :func:`duty_profile`."""
    if idle_s < 0:
        raise ValueError(f"idle_s: must be >= 0, got {idle_s}")
    if segment_s is not None and not segment_s > 0:
        raise ValueError(f"segment_s: must be > 0, got {segment_s}")
    rng = np.random.default_rng(seed)
    phase, period_s = rng.uniform(0, 2 * np.pi), rng.uniform(2.0, 4.0) * 3600.0
    speeds = np.array([n for n in SPEEDS_RPM if n <= max_speed_rpm])

    def ambient(t: float) -> float:
        return round(float(ambient_c + np.sin(phase + 2 * np.pi * t / period_s)), 2)

    if idle_s > 0:
        yield Segment(idle_s, 0.0, 0.0, ambient(0.0))
    t, last = idle_s, 0.0
    while True:
        dur = 60.0 * int(rng.integers(1, 7))
        if segment_s is not None:
            dur = float(segment_s)
        speed = float(rng.choice(speeds[speeds != last]))
        torque = 0.0 if speed == 0 else round(float(rng.uniform(*torque_nm)), 2)
        yield Segment(dur, speed, torque, ambient(t + 0.5 * dur))
        t, last = t + dur, speed


def condition_at(profile: list[Segment], t_s: float) -> Segment:
    """The segment running at plant time ``t_s`` (s from the profile's start; a step k → k+1 uses the
    segment at k's time, as the plant's zero-order hold)."""
    end = 0.0
    for seg in profile:
        end += seg.duration_s
        if t_s < end - 1e-9:
            return seg
    return profile[-1]
