"""The scenario families of the robustness bench, drawn per seed (issue 40 part 1).

Every scenario: the spindle at rest for ``rest_min`` (not counted), then machining for ``hours`` (the
counted minutes). The speed plan is the test-like duty cycle (``simulator.duty``: a new speed every 1–6 min
over 0–7000 rpm, torque 3–15 N·m) unless the family changes it; the ambient is the test's (21 °C) with a
±1 K sinusoid of 2–4 h (the shop's ordinary drift) unless the family changes it.

- ``ambient``: ``ramp`` — from the end of the rest a ramp of ±5–8 K over 2–8 h (ISO 230-3's environmental
  test; the ramp's duration is scaled by ``hours`` / 8 h with its rate kept: the scenario sees its first
  ``hours``), then held; ``daynight`` — a 24-h cycle of ±3–5 K amplitude around 21 °C, the run starting at a
  random hour of it, soaked at that hour's ambient; ``monday`` — the machine soaked 48 h at 21 ± 5 K (sign
  drawn): it starts uniform at that ambient, which stays (±1 K);
- ``duty``: ``spectrum`` — long stretches at speeds the test never held (1000–3000 or 5000–6000 rpm,
  ``hours``/4 each), short alternating cycles (1 min at 6000–7000 rpm, 1 min at rest) and a long idle
  (``hours``/6), in a drawn order;
- ``airflow``: ``h7`` / ``h1`` — that zone's H ×1.5–2 from mid-shift on (a door, a fan);
- ``sensors``: ``open`` (flagged by the DAQ), ``stuck`` (at its last value), ``drift`` (+0.5 °C/h), each from
  ``hours``/3 into the machining; the stuck or the drifting channel (drawn) is one of the MLR's inputs, the
  other and the open one are drawn from the rest;
- ``restarts``: a warm restart at machining minute 60 (half-way when shorter): ``no_state`` without the
  plant's sensor offsets, ``no_state_offsets`` with them (±0.2 °C), ``stored`` with them and the stored state;
- ``machine``: ``fixture`` — the mount restraint changed by ±0.2–0.4 since the commissioning (clipped to
  0–1) and a fixture offset of ±2–5 µm from ``hours``/6 on, tool-setter readings (σ 1 µm) every 30 min.

Every family but ``restarts`` runs on the plant with the seed's sensor offsets (±0.2 °C, the same in its
thermal test).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from benchmarks.robustness.plantrun import Fault, HChange

__all__ = ["FAMILIES", "POOLED", "Scenario", "draw_scenarios"]

FAMILIES = ("ambient", "duty", "airflow", "sensors", "restarts", "machine")
POOLED = ("ambient", "duty", "airflow", "sensors")  # the pooled RMS bar
TEST_AMBIENT_C = 21.0
PROBE_EVERY_MIN = 30.0
PROBE_SD_UM = 1.0


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """One scenario: the plant's plan (duration s, speed rpm, torque N·m) and ambient (°C of plant time s),
    its uniform start (None: the first ambient), the changes and the product's restart/readings."""

    family: str
    name: str
    plan: tuple[tuple[float, float, float], ...]
    ambient: Callable[[float], float]
    rest_min: int
    start_c: float | None = None
    offsets: bool = True
    h_change: HChange | None = None
    faults: tuple[Fault, ...] = ()
    restart: tuple[str, float] | None = None  # (mode, plant time s)
    fixture: tuple[float, float] | None = None  # (plant time s, offset µm)
    restraint: float | None = None  # the plant's mount restraint since the commissioning
    probe_every_min: float | None = None
    info: dict[str, Any] | None = None

    @property
    def key(self) -> str:
        return f"{self.family}.{self.name}"


def _grid(t_s: float) -> float:
    return 300.0 * max(1, round(t_s / 300.0))


def _test_like(rng: np.random.Generator, duration_s: float) -> list[tuple[float, float, float]]:
    """The test-like duty cycle's speeds (``simulator.duty``'s rule) for ``duration_s``."""
    speeds = np.arange(0.0, 7001.0, 500.0)
    out: list[tuple[float, float, float]] = []
    t, last = 0.0, 0.0
    while t < duration_s - 1e-9:
        dur = min(60.0 * int(rng.integers(1, 7)), duration_s - t)
        speed = float(rng.choice(speeds[speeds != last]))
        torque = 0.0 if speed == 0 else round(float(rng.uniform(3.0, 15.0)), 2)
        out.append((dur, speed, torque))
        t, last = t + dur, speed
    return out


def _spectrum(rng: np.random.Generator, duration_s: float) -> list[tuple[float, float, float]]:
    """Long stretches at speeds the test never held, short alternating cycles, a long idle."""
    stretch = _grid(duration_s / 4.0)
    idle = _grid(duration_s / 6.0)
    parts: list[list[tuple[float, float, float]]] = [
        [(stretch, float(rng.choice([1000.0, 1500.0, 2000.0, 2500.0, 3000.0])), 6.0)],
        [(stretch, float(rng.choice([5000.0, 5500.0, 6000.0])), 10.0)],
        [(idle, 0.0, 0.0)],
    ]
    high = float(rng.choice([6000.0, 6500.0, 7000.0]))
    alt = max(60.0, duration_s - 2 * stretch - idle)
    parts.append([(60.0, high, 8.0) if i % 2 == 0 else (60.0, 0.0, 0.0) for i in range(round(alt / 60.0))])
    order = rng.permutation(len(parts))
    return [p for i in order for p in parts[int(i)]]


def draw_scenarios(
    seed: int,
    *,
    hours: float,
    rest_min: int,
    mlr_inputs: tuple[int, ...],
    families: tuple[str, ...] = FAMILIES,
) -> list[Scenario]:
    """The seed's scenarios of ``families`` (module docstring); ``mlr_inputs`` the MLR's sensors (0-based)."""
    rng = np.random.default_rng([seed, 40])
    rest_s = 60.0 * rest_min
    mach_s = 3600.0 * hours
    phase, period = rng.uniform(0, 2 * np.pi), rng.uniform(2.0, 4.0) * 3600.0

    def shop(t: float, centre: float = TEST_AMBIENT_C) -> float:
        return float(centre + np.sin(phase + 2 * np.pi * t / period))

    rest = [(rest_s, 0.0, 0.0)]
    duty = tuple(rest + _test_like(rng, mach_s))
    third = _grid(mach_s / 3.0)
    out: list[Scenario] = []

    if "ambient" in families:
        dk = float(rng.choice([-1.0, 1.0]) * rng.uniform(5.0, 8.0))
        ramp_s = rng.uniform(2.0, 8.0) * 3600.0 * min(1.0, hours / 8.0)

        def ramp(t: float) -> float:
            return shop(t) + dk * float(np.clip((t - rest_s) / ramp_s, 0.0, 1.0))

        amp = float(rng.uniform(3.0, 5.0))
        hour0 = float(rng.uniform(0.0, 24.0))

        def day(t: float) -> float:
            return TEST_AMBIENT_C + amp * float(np.sin(2 * np.pi * (hour0 + t / 3600.0) / 24.0))

        soak = TEST_AMBIENT_C + float(rng.choice([-5.0, 5.0]))

        def monday(t: float) -> float:
            return shop(t, soak)

        out += [
            Scenario(family="ambient", name="ramp", plan=duty, ambient=ramp, rest_min=rest_min,
                     info={"dk_c": round(dk, 2), "ramp_h": round(ramp_s / 3600.0, 2)}),
            Scenario(family="ambient", name="daynight", plan=duty, ambient=day, rest_min=rest_min,
                     info={"amplitude_c": round(amp, 2), "start_hour": round(hour0, 1)}),
            Scenario(family="ambient", name="monday", plan=duty, ambient=monday, rest_min=rest_min,
                     start_c=round(monday(0.0), 2), info={"soak_c": soak}),
        ]  # fmt: skip
    if "duty" in families:
        plan = tuple(rest + _spectrum(rng, mach_s))
        out.append(Scenario(family="duty", name="spectrum", plan=plan, ambient=shop, rest_min=rest_min))
    if "airflow" in families:
        for zone in (7, 1):
            scale = np.ones(7)
            scale[zone - 1] = float(rng.uniform(1.5, 2.0))
            change = HChange(t_s=rest_s + _grid(mach_s / 2.0), scale=tuple(float(s) for s in scale))
            out.append(
                Scenario(
                    family="airflow", name=f"h{zone}", plan=duty, ambient=shop, rest_min=rest_min,
                    h_change=change, info={"factor": round(float(scale[zone - 1]), 3)},
                )
            )  # fmt: skip
    if "sensors" in families:
        others = [c for c in range(32) if c not in mlr_inputs]
        picks = rng.choice(others, size=2, replace=False)
        on_mlr = int(rng.choice(mlr_inputs))
        stuck_on_mlr = bool(rng.integers(2))
        chan = {
            "open": int(picks[0]) + 1,
            "stuck": (on_mlr if stuck_on_mlr else int(picks[1])) + 1,
            "drift": (int(picks[1]) if stuck_on_mlr else on_mlr) + 1,
        }
        for kind, channel in chan.items():
            f = Fault(kind=kind, channel=channel, start_s=rest_s + third)
            out.append(
                Scenario(
                    family="sensors", name=kind, plan=duty, ambient=shop, rest_min=rest_min, faults=(f,),
                    info={"channel": channel, "mlr_input": channel - 1 in mlr_inputs},
                )
            )  # fmt: skip
    if "restarts" in families:
        at = rest_s + min(3600.0, _grid(mach_s / 2.0))
        for name, mode, offsets in (
            ("no_state", "no_state", False),
            ("no_state_offsets", "no_state", True),
            ("stored", "stored", True),
        ):
            out.append(
                Scenario(
                    family="restarts", name=name, plan=duty, ambient=shop, rest_min=rest_min, offsets=offsets,
                    restart=(mode, at),
                )
            )  # fmt: skip
    if "machine" in families:
        d_s = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.4))
        offset = float(rng.choice([-1.0, 1.0]) * rng.uniform(2.0, 5.0))
        out.append(
            Scenario(
                family="machine", name="fixture", plan=duty, ambient=shop, rest_min=rest_min,
                fixture=(rest_s + _grid(mach_s / 6.0), offset), restraint=d_s,
                probe_every_min=PROBE_EVERY_MIN,
                info={"offset_um": round(offset, 2), "restraint_change": round(d_s, 3)},
            )
        )  # fmt: skip
    return out
