"""Virtual plant: the "real spindle" behind the simulated devices and the benchmarks.

It runs the FE model on a finer mesh than the service (no inverse crime) with its own ground truth
``h_true(speed, ambient, torque)``, follows an operating profile and produces the 32 sensor time series as a
DAQ would report them: Gaussian noise, quantisation, constant per-channel offsets and channel faults.

Ground truth H (documented in docs/design/model.md)::

    H_i(n, Ti) = clip(HA_i * (1 + d_i * tanh((n - 3000) / 1500)) * exp(-0.01 * (Ti - 23.2)), 5, 200)

HA is the paper's Table 4 (3000 rpm, 23.2 degC); d_i is solved so that the law passes exactly through Table 10
(4000 rpm, 21.8 degC). Torque does not change H in this truth (it only changes the bearing heat).

Errors::

    PlantError(ValueError)   empty profile, bad segment, bad fault or offsets
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.errors import ModelError
from model.fem import FEModel, Stepper, build_fe_model, make_stepper
from model.geometry import N_CHANNELS, SpindleSpec
from model.inputs import InputSeries, inputs_from_operation
from model.plantmech import PlantMechanics, build_plant_growth
from model.thermoelastic import GrowthModel

H_TABLE4 = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])  # 3000 rpm, 23.2 degC
H_TABLE10 = np.array([79.75, 46.25, 61.89, 45.31, 46.20, 68.23, 11.12])  # 4000 rpm, 21.8 degC
N_A, TI_A = 3000.0, 23.2
N_B, TI_B = 4000.0, 21.8
SPEED_SCALE_RPM = 1500.0
AMBIENT_COEF_PER_K = 0.01
H_CLIP = (5.0, 200.0)
_D = (H_TABLE10 / H_TABLE4 * np.exp(AMBIENT_COEF_PER_K * (TI_B - TI_A)) - 1.0) / np.tanh(
    (N_B - N_A) / SPEED_SCALE_RPM
)

OPEN_CIRCUIT_C = -327.68  # int16 minimum at 0.01 degC/bit
OUT_OF_RANGE_C = 327.67  # int16 maximum
STATUS_OK, STATUS_OPEN, STATUS_RANGE = 0, 1, 2
DEFAULT_SUBSTEPS = 4  # backward Euler at 2.5 s for 10-s samples: not the service's time integration


class PlantError(ModelError, ValueError):
    """Bad plant configuration or profile; the message names the field."""


def h_true(speed_rpm: float, ambient_c: float, torque_nm: float = 0.0) -> NDArray[np.float64]:
    """Ground-truth H1..H7 [W/(m^2 K)] of the virtual plant at speed [rpm], ambient [degC], torque [N m]."""
    del torque_nm  # documented: torque changes the bearing heat, not H
    speed = (1.0 + _D * np.tanh((abs(float(speed_rpm)) - N_A) / SPEED_SCALE_RPM)) * H_TABLE4
    return np.asarray(np.clip(speed * np.exp(-AMBIENT_COEF_PER_K * (ambient_c - TI_A)), *H_CLIP))


@dataclass(frozen=True)
class Segment:
    """One piece of an operating profile: duration [s], speed [rpm], torque [N m], ambient [degC]."""

    duration_s: float
    speed_rpm: float
    torque_nm: float
    ambient_c: float


@dataclass(frozen=True)
class ChannelFault:
    """A fault on ``channel`` (1..32) from ``start_s`` to ``end_s`` [s] (None: to the end).

    kind "open": open circuit, value OPEN_CIRCUIT_C and status 1; "stuck": the value freezes at the last
    reading before start_s, status 0; "range": value OUT_OF_RANGE_C and status 2; "drift": the reading gains
    ``rate_c_per_h`` [°C/h] × the time since start_s, status 0 (a sensor or its cold junction ageing; the
    gain stays at its value at end_s afterwards: a drifted sensor does not come back by itself).
    """

    channel: int
    kind: Literal["open", "stuck", "range", "drift"]
    start_s: float
    end_s: float | None = None
    rate_c_per_h: float = 0.5


@dataclass
class PlantRun:
    """Sampled plant output; n = total steps + 1 (includes t = 0). Condition arrays hold, at sample k, the
    condition applied on step k -> k+1 (the last sample repeats the last step's), as a DAQ would read it."""

    times_s: NDArray[np.float64]  # (n,) [s]
    temps_c: NDArray[np.float64]  # (n, 32) measured [degC]
    truth_c: NDArray[np.float64]  # (n, 32) noise-free [degC]
    ambient_c: NDArray[np.float64]  # (n,) [degC]
    speed_rpm: NDArray[np.float64]  # (n,)
    torque_nm: NDArray[np.float64]  # (n,)
    h_true: NDArray[np.float64]  # (n, 7) [W/(m^2 K)]
    status: NDArray[np.int64]  # (n, 32): 0 ok, 1 open circuit, 2 out of range
    final_field_c: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # plant mesh (N,)
    # with ``run(keep_fields_every=k)``: the full field (m, N) [degC] on the plant mesh at samples 0, k, ...
    # (times ``field_times_s`` (m,) [s]); empty otherwise
    fields_c: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)))
    field_times_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))


def _check_profile(profile: Sequence[Segment], dt_s: float) -> list[int]:
    if not profile:
        raise PlantError("profile: must contain at least one segment")
    steps = []
    for i, seg in enumerate(profile):
        values = (seg.duration_s, seg.speed_rpm, seg.torque_nm, seg.ambient_c)
        if not all(np.isfinite(v) for v in values):
            raise PlantError(f"profile[{i}]: non-finite value")
        if seg.duration_s < dt_s - 1e-9:
            raise PlantError(f"profile[{i}].duration_s: must be >= dt_s ({dt_s}), got {seg.duration_s}")
        steps.append(round(seg.duration_s / dt_s))
    return steps


def _check_faults(faults: Sequence[ChannelFault]) -> tuple[ChannelFault, ...]:
    for i, f in enumerate(faults):
        if not 1 <= f.channel <= N_CHANNELS:
            raise PlantError(f"faults[{i}].channel: must be 1..{N_CHANNELS}, got {f.channel}")
        if f.kind not in ("open", "stuck", "range", "drift"):
            raise PlantError(f"faults[{i}].kind: must be open, stuck, range or drift, got {f.kind!r}")
        if not np.isfinite(f.rate_c_per_h):
            raise PlantError(f"faults[{i}].rate_c_per_h: must be finite, got {f.rate_c_per_h}")
    return tuple(faults)


class _FieldKeeper:
    """Collects the field at every ``every``-th sample while a run marches (``VirtualPlant.run``)."""

    def __init__(self, every: int, field0: NDArray[np.float64]) -> None:
        self.every = every
        self.sample = 0  # samples done so far
        self.samples: list[int] = [0]
        self.fields: list[NDArray[np.float64]] = [field0.copy()]

    def march(
        self, stepper: Stepper, inp: InputSeries, T: NDArray[np.float64], sub: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``stepper.march`` over ``inp`` (sub steps per sample) in pieces ending on kept samples."""
        m = inp.n_steps // sub
        sens = [stepper.fe.sensor_op @ T]
        done = 0
        while done < m:
            piece = min(self.every - self.sample % self.every, m - done)
            part = InputSeries(
                dt_s=inp.dt_s,
                ambient_c=inp.ambient_c[done * sub : (done + piece) * sub],
                q_front_w=inp.q_front_w[done * sub : (done + piece) * sub],
                q_rear_w=inp.q_rear_w[done * sub : (done + piece) * sub],
            )
            last, fine = stepper.march(part, T, keep_fields=False)
            T = last[0]
            sens.append(fine[1:])
            done += piece
            self.sample += piece
            if self.sample % self.every == 0:
                self.samples.append(self.sample)
                self.fields.append(T.copy())
        return np.vstack(sens), T

    def fill(self, n: int, T: NDArray[np.float64]) -> None:
        """``n`` more samples at the converged field ``T`` (the plant's steady shortcut)."""
        for _ in range(n):
            self.sample += 1
            if self.sample % self.every == 0:
                self.samples.append(self.sample)
                self.fields.append(T.copy())


class VirtualPlant:
    """The simulated spindle. ``mesh_size_m`` None uses ``spec.plant_mesh_size_m`` (finer than the service).

    ``substeps``: backward-Euler steps per sample (dt_s / substeps internally); the default 4 (2.5-s steps)
    keeps the plant's time discretisation apart from the service's (exact over each held 10-s step), so no
    bench shares the service's time-step error (issue 15). ``h_law``: the truth H(speed [rpm], ambient [°C],
    torque [N·m]) -> (7,) [W/(m²·K)]; None is ``h_true``.
    ``steady_tol_c``: within a segment, once the sensors change by less than this over
    30 samples, the rest of the segment is filled with the converged values (fast long profiles); 0 disables
    the shortcut.
    ``mechanics``: the plant's own mechanics (``model.plantmech``: mount restraint, α factors), None the
    description's (nominal); its true growth (``growth``, ``growth_um``) comes from them on the plant's mesh,
    built on first use (or ``growth`` given, built with the same mechanics on ``fe``).
    """

    def __init__(
        self,
        spec: SpindleSpec,
        *,
        mesh_size_m: float | None = None,
        noise_c: float = 0.15,
        quant_c: float = 0.01,
        offsets_c: ArrayLike | None = None,
        faults: Sequence[ChannelFault] = (),
        seed: int = 0,
        theta: float = 1.0,
        substeps: int = DEFAULT_SUBSTEPS,
        h_law: Callable[[float, float, float], NDArray[np.float64]] | None = None,
        steady_tol_c: float = 1e-3,
        fe: FEModel | None = None,
        mechanics: PlantMechanics | None = None,
        growth: GrowthModel | None = None,
    ) -> None:
        self.spec = spec
        self.mechanics = mechanics
        self._growth = growth
        self.fe = (
            fe if fe is not None else build_fe_model(spec, mesh_size_m=mesh_size_m or spec.plant_mesh_size_m)
        )
        self.noise_c, self.quant_c, self.seed, self.theta = float(noise_c), float(quant_c), seed, theta
        if int(substeps) < 1:
            raise PlantError(f"substeps: must be >= 1, got {substeps!r}")
        self.substeps = int(substeps)
        off = np.zeros(N_CHANNELS) if offsets_c is None else np.asarray(offsets_c, dtype=float)
        if off.shape != (N_CHANNELS,):
            raise PlantError(f"offsets_c: expected {N_CHANNELS} values, got shape {off.shape}")
        if noise_c < 0 or quant_c < 0:
            raise PlantError("noise_c/quant_c: must be >= 0")
        self.offsets_c = off
        self.faults = _check_faults(faults)
        self.steady_tol_c = steady_tol_c
        self.h_law = h_law if h_law is not None else h_true
        self._steppers: dict[tuple[bytes, float], Stepper] = {}

    @property
    def growth(self) -> GrowthModel:
        """The plant's growth model: its own mechanics (nominal when None) on its own mesh."""
        if self._growth is None:
            mech = self.mechanics if self.mechanics is not None else PlantMechanics.nominal(self.spec)
            self._growth = build_plant_growth(self.spec, self.fe, mech)
        return self._growth

    def growth_um(self, field_c: ArrayLike, t_ref_c: float | ArrayLike) -> NDArray[np.float64]:
        """The true growth [µm] (every output) of plant-mesh fields (N,) or (n, N) over ``t_ref_c``."""
        return np.asarray(self.growth.growth_um(field_c, t_ref_c), dtype=np.float64)

    def _stepper(self, h: NDArray[np.float64], dt_s: float) -> Stepper:
        key = (h.tobytes(), dt_s)
        if key not in self._steppers:
            self._steppers[key] = make_stepper(self.fe, h, dt_s=dt_s, theta=self.theta)
        return self._steppers[key]

    def _segment(
        self,
        seg: Segment,
        n: int,
        dt_s: float,
        field0: NDArray[np.float64],
        chunk: int = 30,
        keep: _FieldKeeper | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Sensors (n, 32) after each step of one segment, and the final field (``keep``: record fields)."""
        sub = self.substeps
        h = np.asarray(self.h_law(seg.speed_rpm, seg.ambient_c, seg.torque_nm), dtype=np.float64)
        stepper = self._stepper(h, dt_s / sub)
        out = np.empty((n, N_CHANNELS))
        done, T = 0, field0
        while done < n:
            m = min(chunk, n - done)
            inp = inputs_from_operation(
                self.spec,
                dt_s=dt_s / sub,
                speed_rpm=np.full(m * sub, seg.speed_rpm),
                torque_nm=seg.torque_nm,
                ambient_c=seg.ambient_c,
            )
            if keep is None:
                last, fine = stepper.march(inp, T, keep_fields=False)
                T = last[0]
            else:  # the same steps in pieces that end on the kept samples (identical numerics)
                fine, T = keep.march(stepper, inp, T, sub)
            sens = fine[::sub]
            out[done : done + m] = sens[1:]
            done += m
            if self.steady_tol_c > 0 and m == chunk and np.abs(sens[-1] - sens[0]).max() < self.steady_tol_c:
                out[done:] = sens[-1]
                if keep is not None:
                    keep.fill(n - done, T)
                break
        return out, T

    def run(
        self,
        profile: Sequence[Segment],
        *,
        dt_s: float = 10.0,
        t0_c: float | ArrayLike | None = None,
        rng: np.random.Generator | None = None,
        keep_fields_every: int = 0,
    ) -> PlantRun:
        """Simulate ``profile`` sampled every ``dt_s`` [s] from t0_c (None: uniform at the first ambient).

        ``keep_fields_every`` k > 0 also keeps the full plant-mesh field at samples 0, k, 2k, ...
        (``PlantRun.fields_c``); the sensors are the same as without (the same steps, marched in pieces).
        """
        steps = _check_profile(profile, dt_s)
        if int(keep_fields_every) < 0:
            raise PlantError(f"keep_fields_every: must be >= 0, got {keep_fields_every!r}")
        t0 = profile[0].ambient_c if t0_c is None else t0_c
        T = np.asarray(t0, dtype=float)
        T = np.full(self.fe.n_nodes, float(T)) if T.ndim == 0 else T.copy()
        if T.shape != (self.fe.n_nodes,):
            raise PlantError(f"t0_c: expected a scalar or shape ({self.fe.n_nodes},), got {T.shape}")
        truth = [self.fe.sensor_op @ T]
        keep = _FieldKeeper(int(keep_fields_every), T) if keep_fields_every else None
        for seg, n in zip(profile, steps, strict=True):
            sens, T = self._segment(seg, n, dt_s, T, keep=keep)
            truth.append(sens)
        run = self._condition_arrays(profile, steps, dt_s)
        run.truth_c = np.vstack(truth)
        run.final_field_c = T
        if keep is not None:
            run.fields_c = np.array(keep.fields)
            run.field_times_s = np.array(keep.samples, dtype=np.float64) * dt_s
        self._measure(run, rng if rng is not None else np.random.default_rng(self.seed))
        return run

    def _condition_arrays(self, profile: Sequence[Segment], steps: list[int], dt_s: float) -> PlantRun:
        idx = np.repeat(np.arange(len(profile)), steps)
        idx = np.append(idx, idx[-1])
        n = idx.size

        def col(name: str) -> NDArray[np.float64]:
            return np.array([getattr(profile[int(i)], name) for i in idx], dtype=np.float64)

        h = np.array([self.h_law(s.speed_rpm, s.ambient_c, s.torque_nm) for s in profile])[idx]
        z = np.zeros((n, N_CHANNELS))
        return PlantRun(
            times_s=np.arange(n, dtype=np.float64) * dt_s,
            temps_c=z,
            truth_c=z,
            ambient_c=col("ambient_c"),
            speed_rpm=col("speed_rpm"),
            torque_nm=col("torque_nm"),
            h_true=h,
            status=np.zeros((n, N_CHANNELS), dtype=np.int64),
        )

    def _measure(self, run: PlantRun, rng: np.random.Generator) -> None:
        meas = run.truth_c + self.offsets_c + self.noise_c * rng.standard_normal(run.truth_c.shape)
        if self.quant_c > 0:
            meas = np.round(meas / self.quant_c) * self.quant_c
            run.ambient_c = np.round(run.ambient_c / self.quant_c) * self.quant_c
        for f in self.faults:
            on = (run.times_s >= f.start_s) & (run.times_s < (np.inf if f.end_s is None else f.end_s))
            c = f.channel - 1
            if f.kind == "open":
                meas[on, c], run.status[on, c] = OPEN_CIRCUIT_C, STATUS_OPEN
            elif f.kind == "range":
                meas[on, c], run.status[on, c] = OUT_OF_RANGE_C, STATUS_RANGE
            elif f.kind == "drift":
                end = np.inf if f.end_s is None else f.end_s
                dt_h = (np.minimum(run.times_s, end) - f.start_s) / 3600.0
                meas[:, c] += f.rate_c_per_h * np.maximum(dt_h, 0.0)
            elif on.any():
                first = int(np.argmax(on))
                meas[on, c] = meas[max(first - 1, 0), c]
        run.temps_c = meas
