"""Error of the reduced model against the full FE on random H and random input histories.

Used at build time (the bound stored with the cache), by the tests and by ``python -m benchmarks model``. The
cases are drawn from their own seed, distinct from the training samples: H half log-uniform and half uniform
in the box, 1–4 piecewise-constant segments of ambient temperature and bearing heat over the window, and a
start that is either uniform or a non-uniform full-FE steady field of another H and load (at the same
ambient).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from model.rom_train import AffineSystem, reference_sensors, steady_field

Array = NDArray[np.float64]


@dataclass(frozen=True)
class CaseInputs:
    """Piecewise-constant inputs of one check case (duck-types ``model.inputs.InputSeries``)."""

    dt_s: float
    ambient_c: Array
    q_front_w: Array
    q_rear_w: Array


@dataclass(frozen=True)
class Case:
    """One random H (7,) [W/(m²·K)] with two input histories: one from a uniform start, one from a
    non-uniform start field; ``t0`` (N, 2) [°C]."""

    h: Array
    inputs: tuple[CaseInputs, CaseInputs]
    t0: Array


class SensorSimulator(Protocol):
    """What the check needs from a reduced model."""

    def simulate_sensors(
        self, h: Array, inputs: Any, t0: float | Array, *, load_scale: Array | None = None
    ) -> Array: ...


def random_h(rng: np.random.Generator, box: tuple[float, float], *, log: bool) -> Array:
    """One H (7,) in the box, log-uniform or uniform."""
    lo, hi = box
    u = rng.random(7)
    return np.asarray(lo * (hi / lo) ** u if log else lo + (hi - lo) * u)


def random_inputs(
    rng: np.random.Generator, *, n_steps: int, dt_s: float, q_max_w: tuple[float, float]
) -> CaseInputs:
    """1–4 segments of constant ambient (15–30 °C) and bearing heat (0..q_max W) over n_steps."""
    n_seg = int(rng.integers(1, 5))
    cuts = np.sort(rng.choice(np.arange(1, n_steps), size=n_seg - 1, replace=False))
    bounds = np.concatenate([[0], cuts, [n_steps]]).astype(int)
    amb, qf, qr = (np.empty(n_steps) for _ in range(3))
    for a, b in itertools.pairwise(bounds):
        amb[a:b] = rng.uniform(15.0, 30.0)
        qf[a:b] = rng.uniform(0.0, q_max_w[0])
        qr[a:b] = rng.uniform(0.0, q_max_w[1])
    return CaseInputs(dt_s=dt_s, ambient_c=amb, q_front_w=qf, q_rear_w=qr)


def random_case(
    fe: AffineSystem,
    rng: np.random.Generator,
    *,
    box: tuple[float, float],
    n_steps: int,
    dt_s: float,
    q_max_w: tuple[float, float],
    log_h: bool,
) -> Case:
    """A random check case. The first history starts from a uniform field (any ambient jump); the second
    from a full-FE steady field of another random H and load at the window's first ambient temperature
    (the ambient is continuous across windows, H and the load are not)."""
    h = random_h(rng, box, log=log_h)
    inputs = (
        random_inputs(rng, n_steps=n_steps, dt_s=dt_s, q_max_w=q_max_w),
        random_inputs(rng, n_steps=n_steps, dt_s=dt_s, q_max_w=q_max_w),
    )
    uniform = np.full(fe.E.shape[0], rng.uniform(15.0, 30.0))
    field = steady_field(
        fe,
        random_h(rng, box, log=True),
        ambient_c=float(inputs[1].ambient_c[0]),
        q_front_w=rng.uniform(0.0, q_max_w[0]),
        q_rear_w=rng.uniform(0.0, q_max_w[1]),
    )
    return Case(h=h, inputs=inputs, t0=np.column_stack([uniform, field]))


def case_reference(
    fe: AffineSystem, case: Case, *, theta: float, ref_substeps: int = 1
) -> tuple[Array, float]:
    """Full-FE sensors (2, n_steps+1, 32) [°C] of both histories of a case, and an estimate of their own
    time-step error [°C]. ``ref_substeps`` 1: the θ-method at the input step (estimate 0: the same scheme as
    the ROM's projection check). s > 1: Richardson extrapolation 2·X(Δt/2s) − X(Δt/s) of two backward-Euler
    runs (first order, so the extrapolation is second order); the estimate is max |X(Δt/2s) − extrapolated|,
    the error of the finer run, an upper bound of the extrapolation's."""

    def run(sub: int) -> Array:
        return np.asarray(
            reference_sensors(
                fe,
                case.h,
                dt_s=case.inputs[0].dt_s,
                ambient_c=np.column_stack([c.ambient_c for c in case.inputs]),
                q_front_w=np.column_stack([c.q_front_w for c in case.inputs]),
                q_rear_w=np.column_stack([c.q_rear_w for c in case.inputs]),
                t0=case.t0,
                theta=theta if sub == 1 else 1.0,
                substeps=sub,
            )
        )

    if ref_substeps <= 1:
        return run(1), 0.0
    coarse, fine = run(ref_substeps), run(2 * ref_substeps)
    extrapolated = 2.0 * fine - coarse
    return extrapolated, float(np.max(np.abs(fine - extrapolated)))


def case_errors(
    rom: SensorSimulator, fe: AffineSystem, case: Case, *, theta: float, ref_substeps: int = 1
) -> Array:
    """Max |ROM − full FE| over sensors and steps [°C] for both histories of a case -> (2,); the full FE is
    ``case_reference`` (``ref_substeps`` > 1: converged in time, for a ROM without time-step error)."""
    return rom_errors(rom, case, case_reference(fe, case, theta=theta, ref_substeps=ref_substeps)[0])


def rom_errors(rom: SensorSimulator, case: Case, full: Array) -> Array:
    """Max |ROM − ``full``| [°C] for both histories of a case -> (2,)."""
    red_uniform = rom.simulate_sensors(case.h[None, :], case.inputs[0], float(case.t0[0, 0]))[0]
    red_field = rom.simulate_sensors(case.h[None, :], case.inputs[1], case.t0[:, 1])[0]
    return np.array([np.max(np.abs(red_uniform - full[0])), np.max(np.abs(red_field - full[1]))])


def error_report(
    rom: SensorSimulator,
    fe: AffineSystem,
    *,
    theta: float,
    box: tuple[float, float],
    n_cases: int,
    seed: int,
    q_max_w: tuple[float, float],
    n_steps: int = 360,
    dt_s: float = 10.0,
    progress: Callable[[str], None] | None = None,
    ref_substeps: int = 1,
) -> dict[str, Any]:
    """Max/mean/95th-percentile sensor error [°C] of the ROM vs the full FE over ``n_cases`` random H, each
    with two random input histories (uniform and non-uniform start). ``ref_substeps`` > 1: against a full FE
    converged in time (``case_reference``), for the ROM as served with its own time integration."""
    rng = np.random.default_rng(seed)
    errors = np.zeros((n_cases, 2))
    ref_err = 0.0
    worst_h = np.zeros(7)
    for i in range(n_cases):
        case = random_case(fe, rng, box=box, n_steps=n_steps, dt_s=dt_s, q_max_w=q_max_w, log_h=i % 2 == 0)
        full, est = case_reference(fe, case, theta=theta, ref_substeps=ref_substeps)
        errors[i], ref_err = rom_errors(rom, case, full), max(ref_err, est)
        if errors[i].max() >= errors.max():
            worst_h = case.h
        if progress is not None and (i + 1) % 10 == 0:
            progress(f"rom check {i + 1}/{n_cases} H samples: max so far {errors.max():.4f} °C")
    return {
        "max_err_c": float(errors.max()) if n_cases else 0.0,
        "mean_err_c": float(errors.mean()) if n_cases else 0.0,
        "p95_err_c": float(np.percentile(errors, 95)) if n_cases else 0.0,
        "n_cases": n_cases,
        "n_histories": 2 * n_cases,
        "max_err_uniform_start_c": float(errors[:, 0].max()) if n_cases else 0.0,
        "max_err_field_start_c": float(errors[:, 1].max()) if n_cases else 0.0,
        "n_steps": n_steps,
        "dt_s": dt_s,
        "ref_substeps": ref_substeps,
        "ref_time_err_c": ref_err,  # the reference's own time-step error (estimate, ``case_reference``)
        "seed": seed,
        "q_max_w": list(q_max_w),
        "box": list(box),
        "worst_h": [float(x) for x in worst_h],
    }
