"""The plant's side of a robustness scenario: its segments, an H change from a time on, sensor faults in the
measured data, and the true growth (issue 40 part 1).

- ``segments``: a speed plan (duration, speed, torque) cut on a 5-min grid, each piece at the scenario's
  ambient at its middle (the plant takes one ambient per segment);
- an airflow change (``HChange``: H scaled by a factor per zone from ``t_s`` on) runs the plant in two
  parts, the second from the first's final field with the scaled H law, joined into one run
  (``concat_runs``);
- ``inject_faults``: a channel open (value and DAQ status as ``model.plant`` writes them), stuck at its last
  reading, or drifting by ``rate_c_per_h`` (status ok: neither flagged). The plant's own ``ChannelFault`` has
  no drift; this is the one function to swap when the simulated DAQ gets one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from model.plant import OPEN_CIRCUIT_C, STATUS_OPEN, PlantRun, Segment

__all__ = ["Fault", "HChange", "concat_runs", "inject_faults", "scaled_law", "segments"]

GRID_S = 300.0


@dataclass(frozen=True, kw_only=True)
class Fault:
    """A sensor fault on ``channel`` (1..32) from ``start_s`` on: ``open``, ``stuck`` or ``drift``."""

    kind: str
    channel: int
    start_s: float
    rate_c_per_h: float = 0.5


@dataclass(frozen=True, kw_only=True)
class HChange:
    """H multiplied by ``scale`` (7,) from plant time ``t_s`` on (a multiple of the 5-min grid)."""

    t_s: float
    scale: tuple[float, ...]


def segments(plan: Sequence[tuple[float, float, float]], ambient: Callable[[float], float]) -> list[Segment]:
    """The plan's (duration s, speed rpm, torque N·m) pieces cut on the 5-min grid, each at ``ambient`` (°C,
    of plant time s) at its middle."""
    out: list[Segment] = []
    t = 0.0
    for dur, speed, torque in plan:
        end = t + dur
        while t < end - 1e-9:
            cut = min(end, (np.floor(t / GRID_S + 1e-9) + 1.0) * GRID_S)
            out.append(Segment(cut - t, speed, torque, round(float(ambient(0.5 * (t + cut))), 2)))
            t = cut
    return out


def scaled_law(
    law: Callable[..., Any], scale: Sequence[float]
) -> Callable[[float, float, float], np.ndarray]:
    """``law`` with each zone's H multiplied by ``scale``."""
    s = np.asarray(scale, dtype=float)

    def scaled(speed_rpm: float, ambient_c: float = 0.0, torque_nm: float = 0.0) -> np.ndarray:
        return np.asarray(law(speed_rpm, ambient_c, torque_nm), dtype=float) * s

    return scaled


def concat_runs(a: PlantRun, b: PlantRun) -> PlantRun:
    """Run ``b`` (started from ``a``'s final field) after ``a``: ``a``'s last sample is ``b``'s first."""
    shift = float(a.times_s[-1])

    def cat(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.concatenate([x[:-1], y])

    return replace(
        b,
        times_s=cat(a.times_s, b.times_s + shift),
        temps_c=cat(a.temps_c, b.temps_c),
        truth_c=cat(a.truth_c, b.truth_c),
        ambient_c=cat(a.ambient_c, b.ambient_c),
        speed_rpm=cat(a.speed_rpm, b.speed_rpm),
        torque_nm=cat(a.torque_nm, b.torque_nm),
        h_true=cat(a.h_true, b.h_true),
        status=cat(a.status, b.status),
        fields_c=cat(a.fields_c, b.fields_c),
        field_times_s=cat(a.field_times_s, b.field_times_s + shift),
    )


def inject_faults(run: PlantRun, faults: Sequence[Fault]) -> PlantRun:
    """The run with ``faults`` in its measured temperatures (module docstring); the truth untouched."""
    temps = run.temps_c.copy()
    status = run.status.copy()
    for f in faults:
        if not 1 <= f.channel <= temps.shape[1]:
            raise ValueError(f"faults.channel: must be 1..{temps.shape[1]}, got {f.channel}")
        c = f.channel - 1
        on = run.times_s >= f.start_s
        if not on.any():
            continue
        first = int(np.argmax(on))
        if f.kind == "open":
            temps[on, c], status[on, c] = OPEN_CIRCUIT_C, STATUS_OPEN
        elif f.kind == "stuck":
            temps[on, c] = temps[max(first - 1, 0), c]
        elif f.kind == "drift":
            temps[on, c] += f.rate_c_per_h * (run.times_s[on] - f.start_s) / 3600.0
        else:
            raise ValueError(f"faults.kind: must be open, stuck or drift, got {f.kind!r}")
    return replace(run, temps_c=temps, status=status)
