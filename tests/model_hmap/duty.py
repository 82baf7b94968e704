"""Seeded machining duty cycles on the virtual plant (finer mesh, its own h_true) for the H-map tests."""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from model.hmap_identify import SpeedWindow
from model.inputs import inputs_from_operation
from model.plant import PlantRun, Segment, VirtualPlant

SPEEDS_RPM = np.arange(0.0, 7001.0, 500.0)
SERVICE_ROM_RANK = 30  # the service's default (service.modelload.ModelRef), same cache file


def load_service_model() -> Any:
    """Spec, FE model (service mesh) and the cached reduced model the service uses by default, loaded with
    ``model`` only (the service layer is being restructured): ``.spec``, ``.fe``, ``.rom``."""
    from model.fem import build_fe_model
    from model.geometry import load_spindle
    from model.rom import load_or_build_rom

    cache = os.environ.get("CHTC_CACHE_DIR") or str(
        Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "spindle-chtc"
    )
    Path(cache).mkdir(parents=True, exist_ok=True)
    spec = load_spindle()
    fe = build_fe_model(spec)
    rom = load_or_build_rom(fe, spec, Path(cache), rank=SERVICE_ROM_RANK, box=(5.0, 200.0))
    # model.rom_segments implements the plain θ-step (substeps=1); the served model integrates each held step
    # exactly since issue 15 (docs/design/hmap.md, "Hand-off"): compare like with like
    return SimpleNamespace(spec=spec, fe=fe, rom=replace(rom, substeps=1))


def duty_profile(seed: int, *, duration_s: float, ambient_c: float = 22.0) -> list[Segment]:
    """Speed changes every 1–6 min (whole minutes) among 0, 500, ..., 7000 rpm, torque 3–15 N·m (0 at rest),
    ambient drifting within ±1 °C (a slow sinusoid of random phase, held per segment)."""
    rng = np.random.default_rng(seed)
    phase, period_s = rng.uniform(0, 2 * np.pi), rng.uniform(2.0, 4.0) * 3600.0
    out: list[Segment] = []
    t, last = 0.0, -1.0
    while t < duration_s - 1e-9:
        dur = min(60.0 * int(rng.integers(1, 7)), duration_s - t)
        speed = float(rng.choice(SPEEDS_RPM[last != SPEEDS_RPM]))
        torque = 0.0 if speed == 0 else float(rng.uniform(3.0, 15.0))
        amb = ambient_c + np.sin(phase + 2 * np.pi * (t + 0.5 * dur) / period_s)
        out.append(Segment(dur, speed, torque, round(float(amb), 2)))
        t, last = t + dur, speed
    return out


@dataclass(frozen=True)
class DutyRun:
    profile: list[Segment]
    run: PlantRun


def run_duty(plant: VirtualPlant, seed: int, *, duration_s: float, dt_s: float = 10.0) -> DutyRun:
    profile = duty_profile(seed, duration_s=duration_s)
    return DutyRun(profile, plant.run(profile, dt_s=dt_s, rng=np.random.default_rng(seed + 1000)))


def window(spec: Any, run: PlantRun, k0: int, k1: int, t0: Any) -> SpeedWindow:
    """Samples k0..k1 of a plant run as a SpeedWindow (steps k0..k1-1) starting from t0."""
    speed = run.speed_rpm[k0:k1]
    inputs = inputs_from_operation(
        spec, dt_s=float(run.times_s[1] - run.times_s[0]), speed_rpm=speed, torque_nm=run.torque_nm[k0:k1],
        ambient_c=run.ambient_c[k0:k1],
    )  # fmt: skip
    return SpeedWindow(inputs, speed, run.temps_c[k0 : k1 + 1], np.ones(32, dtype=bool), t0)
