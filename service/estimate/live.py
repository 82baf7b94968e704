"""The live temperature field: the FE model advanced with the measured inputs and the current H.

Each accepted sample advances the full FE state (``model.fem.FEModel``, backward Euler like
``model.fem.simulate``'s default θ = 1) on a fixed grid of ``dt_s`` (the sample period: jittered sample
times never refactorise) with the previous sample's inputs held (zero-order hold: the convention of the
identification window, ``service.identify.window``, of ``model.inputs.InputSeries`` and of the plant) and the
bearing heat from ``model.inputs.inputs_from_operation``. The factorised step
(``model.fem.make_stepper``) is cached per H; ``prepare(h)`` builds it off the event loop so that a new H
never stalls the service, and a step is then a pair of sparse triangular solves.

It serves the field *now* (lifted to the mesh: it *is* the mesh field), the predicted sensor temperatures, the
steady state the spindle is heading to under the current inputs and H, and snapshots of past fields that the
identification window uses as its initial field (``field_at``).

It also keeps, per rebase, the covariance of the rebased state's error that the identification reported
(``model.carry.StateCovariance``, reduced coordinates; opaque here): ``covariance_at(t)`` is the one a window
starting at ``t`` inherits (the latest rebase at or before ``t``), which the worker carries to ``t``.

Before the first sample the state is unknown: ``initialize`` sets a uniform field (the service uses the mean
of the good sensors of the first sample). Non-finite inputs (CAN down) hold the last valid ones.

Errors::

    LiveStateError(RuntimeError)   asked for a field before ``initialize`` / with no snapshot old enough
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["LiveModel", "LiveStateError", "Snapshot"]


class LiveStateError(RuntimeError):
    """The live state cannot answer yet (not initialised, or no snapshot that old)."""


@dataclass(frozen=True, eq=False)
class Snapshot:
    t: float  # s (sample time axis)
    field_c: np.ndarray  # (N,) °C
    # descends from the initialisation's guess (uniform at the first sample's mean) with no rebase since: its
    # error is (nearly) that guess's uniform offset
    initial: bool = False


@dataclass(frozen=True)
class _Inputs:
    ambient_c: float
    speed_rpm: float
    torque_nm: float


class LiveModel:
    """FE state estimate; ``fe`` is a ``model.fem.FEModel``, ``spec`` a ``model.geometry.SpindleSpec``."""

    def __init__(
        self,
        fe: Any,
        spec: Any,
        *,
        h: np.ndarray,
        dt_s: float = 10.0,
        load_scale: tuple[float, float] = (1.0, 1.0),
        snapshot_every_s: float = 60.0,
        keep_s: float = 3 * 3600.0,
        recent_steps: int = 64,
    ) -> None:
        self.fe = fe
        self.spec = spec
        self.h = np.asarray(h, dtype=float).copy()
        self.dt_s = float(dt_s)
        self.load_scale = tuple(float(x) for x in load_scale)
        self.snapshot_every_s = snapshot_every_s
        self._snapshots: deque[Snapshot] = deque(maxlen=max(2, int(keep_s / snapshot_every_s) + 2))
        self._recent: deque[Snapshot] = deque(maxlen=max(1, recent_steps))
        # every rebase since initialize() (t, its covariance | None): empty while the state is the guess's
        self._rebases: deque[tuple[float, Any]] = deque(maxlen=self._snapshots.maxlen)
        self._t: float | None = None
        self._T: np.ndarray | None = None
        self._last_inputs: _Inputs | None = None
        self._stepper_key: bytes | None = None  # the H the stepper was built for
        self._stepper: Any = None
        self._steady_key: tuple[Any, ...] | None = None
        self._steady: np.ndarray | None = None
        self.steps = 0

    # --- state ----------------------------------------------------------------------------------------
    @property
    def initialized(self) -> bool:
        return self._T is not None

    @property
    def t(self) -> float:
        if self._t is None:
            raise LiveStateError("the live state has not been initialised (no sample yet)")
        return self._t

    def initialize(self, t: float, field_c: float | np.ndarray, inputs: tuple[float, float, float]) -> None:
        """Start at ``t`` (s) from a uniform temperature or an (N,) field; inputs (ambient, speed, torque)."""
        n = self.fe.n_nodes
        uniform = np.ndim(field_c) == 0
        self._T = np.full(n, field_c, dtype=float) if uniform else np.asarray(field_c, float).copy()
        self._t = float(t)
        self._last_inputs = _Inputs(*inputs)
        self._snapshots.clear()
        self._recent.clear()
        self._rebases.clear()
        first = Snapshot(self._t, self._T.copy(), initial=True)
        self._snapshots.append(first)
        self._recent.append(first)

    def prepare(self, h: np.ndarray) -> Any:
        """The factorised step for H (7,) (``model.fem.make_stepper``); pure, may run in a thread."""
        from model.fem import make_stepper

        return make_stepper(self.fe, np.asarray(h, dtype=float), dt_s=self.dt_s)

    def set_h(
        self, h: np.ndarray, load_scale: tuple[float, float] | None = None, *, stepper: Any = None
    ) -> None:
        """Use new H (7,) W/(m²·K) (and bearing-heat scales) from the next step on.

        ``stepper`` is ``prepare(h)`` computed ahead (off the event loop); otherwise the next step factorises.
        """
        self.h = np.asarray(h, dtype=float).copy()
        if load_scale is not None:
            self.load_scale = tuple(float(x) for x in load_scale)
        if stepper is not None and np.array_equal(np.asarray(stepper.h), self.h):
            self._stepper, self._stepper_key = stepper, self.h.tobytes()

    def push(self, t: float, *, ambient_c: float, speed_rpm: float, torque_nm: float) -> None:
        """Advance the state towards sample time ``t`` (s) with the previous sample's inputs held.

        The state moves on a fixed grid of ``dt_s`` (jittered sample times do not refactorise): it advances
        by ``round((t - t_state) / dt_s)`` steps, so its time stays within ``dt_s/2`` of the newest sample.
        """
        if self._T is None or self._t is None or self._last_inputs is None:
            raise LiveStateError("initialize() the live state before pushing samples")
        new = self._valid_inputs(ambient_c, speed_rpm, torque_nm)
        n = int(np.floor((float(t) - self._t) / self.dt_s + 0.5))
        if n <= 0:
            self._last_inputs = new
            return
        for k, field_c in self._march(self._T, n, self._last_inputs):
            snap = Snapshot(self._t + k * self.dt_s, field_c, initial=not self._rebases)
            self._recent.append(snap)
            if snap.t - self._snapshots[-1].t >= self.snapshot_every_s - 1e-9:
                self._snapshots.append(snap)
        self._T = self._recent[-1].field_c
        self._t = self._recent[-1].t
        self._last_inputs = new
        self.steps += n

    def mark(self, t: float) -> Snapshot:
        """Keep the field of the latest step at or before ``t`` (s) as a snapshot (a window can start there).

        Called at a condition change, whose start lies up to the hold time in the past.
        """
        older = [s for s in self._recent if s.t <= t + 0.5 * self.dt_s]  # sample times jitter around the grid
        if not older:
            return self.field_at(t)
        snap = older[-1]
        if all(s.t != snap.t for s in self._snapshots):
            kept = sorted([*self._snapshots, snap], key=lambda s: s.t)
            self._snapshots.clear()
            self._snapshots.extend(kept[-(self._snapshots.maxlen or len(kept)) :])
        return snap

    def rebase(self, t: float, field_c: np.ndarray, raw: Any, *, covariance: Any = None) -> None:
        """Restart from ``field_c`` (N,) at ``t`` (s) and replay the samples of ``raw``.

        Used when an identification finishes: the fitted model's field at the window end (computed with the
        new H from the window's initial field) replaces the state that was advanced with the old H.
        ``raw`` is a ``service.identify.window.RawWindow`` from at least half a step before ``t`` up to the
        newest
        sample. Every sample of it is pushed again from ``t`` (the ``push`` convention): the ones within half
        a step of ``t`` or before only set the inputs held from ``t`` on, the later ones advance the state.
        With no sample in ``raw`` the state restarts at ``t`` holding the current inputs. ``covariance`` is
        that field's error covariance (None: unknown), returned by ``covariance_at`` for windows starting at
        or after ``t``.
        """
        if self._t is None:
            raise LiveStateError("the live state has not been initialised (no sample yet)")
        self._T = np.asarray(field_c, dtype=float).copy()
        self._t = float(t)
        for dq in (self._snapshots, self._recent):
            kept = [s for s in dq if s.t < t - 1e-9]
            dq.clear()
            dq.extend(kept)
        old = [c for c in self._rebases if c[0] < t - 1e-9]
        self._rebases.clear()
        self._rebases.extend([*old, (float(t), covariance)])
        self._snapshots.append(Snapshot(self._t, self._T))
        self._recent.append(Snapshot(self._t, self._T))
        times = np.asarray(raw.times_s, dtype=float)
        for k in range(len(times)):
            self.push(
                float(times[k]),
                ambient_c=float(raw.ambient_c[k]),
                speed_rpm=float(raw.speed_rpm[k]),
                torque_nm=float(raw.torque_nm[k]),
            )

    # --- queries --------------------------------------------------------------------------------------
    def field_now(self) -> Snapshot:
        if self._T is None or self._t is None:
            raise LiveStateError("the live state has not been initialised (no sample yet)")
        return Snapshot(self._t, self._T.copy(), initial=not self._rebases)

    def sensors_now(self) -> np.ndarray:
        """Predicted temperatures (32,) °C at the sensors."""
        return np.asarray(self.fe.sensor_op @ self.field_now().field_c).ravel()

    def field_at(self, t: float) -> Snapshot:
        """The latest snapshot at or before ``t`` (s), up to half a step later (sample-time jitter)."""
        older = [s for s in self._snapshots if s.t <= t + 0.5 * self.dt_s]
        if not older:
            raise LiveStateError(f"no live-state snapshot at or before t={t:.0f} s")
        return older[-1]

    def covariance_at(self, t: float) -> Any:
        """The error covariance of the latest rebase at or before ``t`` (s); None if it had none, or if no
        rebase came since the start (the initial guess: ``Snapshot.initial`` and its offset fit)."""
        older = [c for t_s, c in self._rebases if t_s <= t + 0.5 * self.dt_s]
        return older[-1] if older else None

    def first_snapshot_after(self, t: float) -> Snapshot:
        """The earliest snapshot at or after ``t`` (s): a window starting there has a known initial field."""
        newer = [s for s in self._snapshots if s.t >= t - 1e-9]
        if not newer:
            raise LiveStateError(f"no live-state snapshot at or after t={t:.0f} s")
        return newer[0]

    def steady(self) -> np.ndarray:
        """Steady field (N,) °C for the current H and the last inputs (cached until either changes)."""
        from model.fem import steady_state

        if self._last_inputs is None:
            raise LiveStateError("the live state has not been initialised (no sample yet)")
        qf, qr = self._heat(self._last_inputs)
        key = (self.h.tobytes(), round(self._last_inputs.ambient_c, 3), round(qf, 4), round(qr, 4))
        if key != self._steady_key or self._steady is None:
            self._steady = steady_state(
                self.fe, self.h, ambient_c=self._last_inputs.ambient_c, q_front_w=qf, q_rear_w=qr
            )
            self._steady_key = key
        return np.asarray(self._steady).copy()

    # --- numerics -------------------------------------------------------------------------------------
    def _valid_inputs(self, ambient_c: float, speed_rpm: float, torque_nm: float) -> _Inputs:
        last = self._last_inputs
        vals = (ambient_c, speed_rpm, torque_nm)
        olds = _astuple(last) if last is not None else (math.nan,) * 3
        return _Inputs(*(v if math.isfinite(v) else o for v, o in zip(vals, olds, strict=True)))

    def _heat(self, inp: _Inputs) -> tuple[float, float]:
        from model.inputs import inputs_from_operation

        series = inputs_from_operation(
            self.spec,
            dt_s=1.0,
            speed_rpm=np.array([inp.speed_rpm]),
            torque_nm=np.array([inp.torque_nm]),
            ambient_c=np.array([inp.ambient_c]),
        )
        return (
            float(series.q_front_w[0]) * self.load_scale[0],
            float(series.q_rear_w[0]) * self.load_scale[1],
        )

    def _march(self, T: np.ndarray, n: int, inp: _Inputs) -> list[tuple[int, np.ndarray]]:
        """``n`` steps of ``dt_s`` from ``T`` with constant inputs -> [(step number, field)].

        Every step's field for short advances; after a long gap only the final one (memory).
        """
        from model.inputs import InputSeries

        if self._stepper_key != self.h.tobytes() or self._stepper is None:
            self._stepper = self.prepare(self.h)
            self._stepper_key = self.h.tobytes()
        qf, qr = self._heat(inp)
        series = InputSeries(self.dt_s, np.full(n, inp.ambient_c), np.full(n, qf), np.full(n, qr))
        keep = n <= (self._recent.maxlen or 1)
        fields, _ = self._stepper.march(series, T, keep_fields=keep)
        if keep:
            return [(k + 1, np.asarray(fields[k + 1])) for k in range(n)]
        return [(n, np.asarray(fields[-1]))]


def _astuple(x: _Inputs) -> tuple[float, float, float]:
    return (x.ambient_c, x.speed_rpm, x.torque_nm)
