"""The filtered live state: ``model.estimator`` behind the interface the service's core uses (pure, no I/O).

Replaces the open-loop ``service.estimate.live.LiveModel`` (docs/design/estimator.md, "Service adapter"). Each
sample is ``push``-ed with its inputs (ambient, speed, torque: the bearing heats from
``model.inputs.inputs_from_operation``), its 32 temperatures, the usable mask (quality OK) and the
calibration's offsets: the reduced state advances on a fixed grid of ``dt_s`` with the previous sample's
inputs held (the ``LiveModel.push`` convention) and is corrected by the usable channels (Schmidt–Kalman
filter, ``model.estimator``). It serves the mean and 1σ of the field and of the sensors now, keeps
snapshots of the estimate (mean and covariance) for identification windows (``field_at``,
``covariance_at``, ``mark``), the NIS per sample and the convergence test that gates identification after a
(re)start.

Compared with ``LiveModel``:

- ``set_h`` takes effect from the next step; no ``prepare``/stepper (a new H costs one r × r
  eigendecomposition, < 1 ms); ``load_scale`` as there.
- no ``rebase``: the measurements keep the field right, so an identification's end field is not needed (and
  replaying samples would count them twice). ``covariance_at`` returns the filter's own covariance (r, r)
  [°C², reduced coordinates] at the snapshot: ``identify(start_cov=...)`` directly, no gap propagation.
- ``initialize`` starts from a wide prior (``model.estimator.wide_prior``) at the ambient, not from a
  confident uniform guess; a gap longer than ``max_gap_s`` restarts from it.
- ``Snapshot.initial`` is True while the state has not yet passed the convergence test since the (re)start:
  windows should not start there (``ready_at``).

- a belief that stops being a distribution (``model.estimator.CovarianceError``: a non-finite or negative
  variance, a covariance not positive semi-definite) is never served: the state restarts from the prior on
  that sample, not converged (``SampleUpdate.restarted``, ``reason``; ``last_restart``), as after a long gap.

Errors::

    LiveStateError(RuntimeError)   (``service.estimate.live``) asked before ``initialize`` / no snapshot
    model.estimator.EstimatorError bad arrays (shape, H <= 0), the field named
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from model.estimator import (
    Convergence,
    CovarianceError,
    Estimate,
    NoiseModel,
    StateEstimator,
    StepInput,
    StepResult,
    convergence,
    field_std,
    heated_prior,
    rescale_cross,
    wide_prior,
)
from model.estimator import usable as usable_channels
from service.contracts.checkpoint import LiveCheckpoint
from service.estimate.convergegate import ConvergenceGate
from service.estimate.faultwatch import FaultWatch
from service.estimate.live import LiveStateError
from service.estimate.nistrack import NisTrack
from service.estimate.offsetbias import OffsetBias, kalman_gain
from service.estimate.sensorfaults import FaultChange, FaultMonitorSettings, SensorFault
from service.estimate.snapshots import SnapshotBook

__all__ = [
    "GUESSED_H_REL",
    "FilterSettings",
    "FilterView",
    "FilteredState",
    "LiveStateError",
    "SampleUpdate",
    "StateSnapshot",
    "h_rel_from_ci",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FilterSettings:
    """Tuning of the filtered state (docs/design/estimator.md): noise, prior, convergence test and memory.

    ``prior`` the restart prior's shape: "heated" (the steady heated fields' second moment plus a small
    isotropic part, ``model.estimator.heated_prior``) or "wide" (isotropic, ``wide_prior``);
    ``prior_sigma_c`` [°C] 1σ of the prior's uniform offset (and of the "wide" shape part); ``nis_window``
    samples of the NIS health test (verdict, ``inconsistent_after_s``); ``converge_nis_samples`` samples of
    the NIS part of the convergence gate (shorter: a χ² test over 6 × 32 dof already rejects an
    inconsistent start, and the gate delays every identification after a (re)start);
    ``sensor_std_bound_c``/``field_rms_bound_c`` [°C] the convergence bounds;
    ``max_gap_s`` [s] a longer gap between samples restarts from the wide prior, and a longer run of samples
    without a usable temperature (a DAQ outage with CAN alive: the state runs open loop) holds identification
    windows back until the state passes the convergence test again on data (``ready_at``); snapshots every
    ``snapshot_every_s`` [s] for ``keep_s`` [s], the last ``recent_steps`` steps for ``mark``;
    ``inconsistent_after_s`` [s]: the NIS window above its band this long is reported (``FilterView``);
    ``reacquire_restart_p``: after such an open-loop run, a first update whose NIS has a χ² upper-tail
    probability below this restarts the state from the prior on that sample (the prediction left its band:
    the held inputs were not the machine's, CAN down too).
    """

    noise: NoiseModel = field(default_factory=NoiseModel)
    prior: str = "heated"  # "heated" (model.estimator.heated_prior) or "wide" (isotropic shape, wide_prior)
    prior_sigma_c: float = 5.0
    nis_window: int = 30
    converge_nis_samples: int = (
        6  # the convergence gate's NIS window (1 min at 10 s: 192 dof with 32 channels)
    )
    sensor_std_bound_c: float = 0.1
    field_rms_bound_c: float = 1.0
    max_gap_s: float = 300.0
    snapshot_every_s: float = 60.0
    keep_s: float = 3 * 3600.0
    recent_steps: int = 64
    inconsistent_after_s: float = 600.0  # NIS window "high" this long [s]: a persistent inconsistency
    # after an open-loop run longer than max_gap_s, the first update on data whose NIS is this improbable
    # (χ² upper tail) restarts the state from the prior on that sample instead of correcting it
    reacquire_restart_p: float = 1e-6
    # the stuck/drifting channel monitor (service.estimate.sensorfaults; None: off): a channel it finds is
    # left out of the updates until it recovers
    faults: FaultMonitorSettings | None = field(default_factory=FaultMonitorSettings)


@dataclass(frozen=True, eq=False)
class StateSnapshot:
    """The estimate at ``t`` [s]: reduced ``mean`` (r,) [°C] and ``cov`` (r, r) [°C²]; ``initial`` while
    not yet converged since the (re)start. ``field_c`` (N,) [°C] is lifted on first use."""

    t: float
    mean: Array
    cov: Array
    initial: bool
    basis: Array = field(repr=False)

    @cached_property
    def field_c(self) -> Array:
        """Mean field V·a [°C] on the service mesh (N,)."""
        return np.asarray(self.basis @ self.mean)

    @property
    def field_std_c(self) -> Array:
        """1σ of the field [°C] per node (N,)."""
        return field_std(self.basis, self.cov)


@dataclass(frozen=True)
class SampleUpdate:
    """What one ``push`` did: ``t`` [s] of the state, ``steps`` advanced, ``nis`` over ``dof`` used channels
    (0, 0 without an update), the NIS window's ``verdict`` ("filling", "ok", "high", "low"), whether the
    state ``restarted`` from the wide prior and why (``reason``: "start", "gap", "prediction lost",
    "covariance: ..."; "" when it did not)."""

    t: float
    steps: int
    nis: float
    dof: int
    verdict: str
    restarted: bool = False
    reason: str = ""
    faults: tuple[FaultChange, ...] = ()  # sensor faults detected or recovered on this sample


@dataclass(frozen=True, eq=False, kw_only=True)
class FilterView:
    """An immutable copy of the filtered state for readers on other threads (``FilteredState.view``).

    ``t`` [s] of the estimate; reduced ``mean`` (r,) [°C] and ``cov`` (r, r) [°C²] (read-only copies);
    ``basis`` (N, r) and ``sensor_rows`` (32, r) the reduced model's (shared, read-only); ``sigma_model_c``
    [°C] the model's error at the sensors outside the state; ``h`` (7,) [W/(m²·K)], ``load_scale`` and the
    held ``inputs`` (ambient °C, speed rpm, torque N·m) that the steady field is computed for
    (``service.estimate.live.steady_field``). Health: ``started_at``/``converged_at`` [s] (None: not yet
    converged since the (re)start, then ``reason`` says why), the last sample's ``nis`` over ``nis_dof``
    channels, the NIS window's ``verdict``, Σ NIS / Σ dof and its χ² ``nis_band``, and ``high_since`` [s]
    (the verdict "high" since then; None: not high). The field's 1σ is computed on first use (O(N·r²))."""

    t: float
    mean: Array
    cov: Array
    basis: Array = field(repr=False)
    sensor_rows: Array = field(repr=False)
    sigma_model_c: float
    h: tuple[float, ...]
    load_scale: tuple[float, float]
    inputs: tuple[float, float, float]
    started_at: float
    converged_at: float | None
    reason: str
    nis: float
    nis_dof: int
    verdict: str
    nis_sum: float
    nis_sum_dof: int
    nis_band: tuple[float, float]
    high_since: float | None
    inconsistent_after_s: float
    # the unknown sensor offsets' share of ``cov`` (r, r) [°C²] (service.estimate.offsetbias; None: not kept)
    offset_cov: Array | None = None
    # channels left out of the updates as stuck or drifting (service.estimate.sensorfaults), by channel
    sensor_faults: tuple[SensorFault, ...] = ()

    @property
    def converged(self) -> bool:
        return self.converged_at is not None

    @cached_property
    def field_c(self) -> Array:
        """Mean field V·a [°C] per node (N,), read-only."""
        return _frozen(self.basis @ self.mean)

    @cached_property
    def field_std_c(self) -> Array:
        """1σ of the field [°C] per node (N,), read-only."""
        return _frozen(field_std(self.basis, self.cov))

    @cached_property
    def sensors_c(self) -> Array:
        """Estimated true temperatures (32,) [°C] at the sensors (offset-corrected frame), read-only."""
        return _frozen(self.sensor_rows @ self.mean)

    @cached_property
    def sensors_std_c(self) -> Array:
        """1σ (32,) [°C] of the sensors' true temperatures (state and model error), read-only."""
        state = field_std(self.sensor_rows, self.cov)
        return _frozen(np.sqrt(state**2 + self.sigma_model_c**2))

    def inconsistent(self, t: float) -> bool:
        """Whether the NIS has been above its band for at least ``inconsistent_after_s`` at ``t`` [s]."""
        return self.high_since is not None and t - self.high_since >= self.inconsistent_after_s


GUESSED_H_REL = 1.0  # the considered H error (relative 1σ) of an H that no identification gave: 100 %


def h_rel_from_ci(h: ArrayLike, hi: ArrayLike) -> NDArray[np.float64]:
    """The relative 1σ of H (7,) from its 95 % CI's upper end (7,): σ(log H) = log(hi/h)/1.96 (the
    filter's considered H error for ``FilteredState.set_h(h_rel=...)``, which clips it to 0.05–1); a
    non-finite one (no CI) is ``GUESSED_H_REL``."""
    h_arr = np.asarray(h, dtype=np.float64)
    hi_arr = np.asarray(hi, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.log(np.maximum(hi_arr / h_arr, 1.0)) / 1.96
    return np.where(np.isfinite(rel), rel, GUESSED_H_REL)


def _frozen(a: Array) -> Array:
    out = np.asarray(a, dtype=np.float64)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class _Inputs:
    ambient_c: float
    speed_rpm: float
    torque_nm: float


def _held(old: _Inputs | None, vals: tuple[float, float, float]) -> _Inputs:
    """``vals`` (ambient °C, speed rpm, torque N·m), a non-finite one replaced by ``old``'s (NaN: none)."""
    olds = (math.nan,) * 3 if old is None else (old.ambient_c, old.speed_rpm, old.torque_nm)
    return _Inputs(*(float(v) if math.isfinite(v) else o for v, o in zip(vals, olds, strict=True)))


def _bearing_heat(spec: Any, inp: _Inputs, load_scale: tuple[float, float]) -> tuple[float, float]:
    """The front and rear bearing heats [W] at ``inp`` (``model.inputs``), times ``load_scale``."""
    from model.inputs import inputs_from_operation

    series = inputs_from_operation(
        spec,
        dt_s=1.0,
        speed_rpm=np.array([inp.speed_rpm]),
        torque_nm=np.array([inp.torque_nm]),
        ambient_c=np.array([inp.ambient_c]),
    )
    return float(series.q_front_w[0]) * load_scale[0], float(series.q_rear_w[0]) * load_scale[1]


def _with_rms(sigma: float, sd: Array) -> float:
    """``sigma`` and the RMS of ``sd`` in quadrature (the same unit)."""
    return math.hypot(sigma, float(np.sqrt(np.mean(sd**2))) if sd.size else 0.0)


class FilteredState:
    """Closed-loop live state on a ``ReducedModel`` ``rom`` for the spindle ``spec``; H (7,) [W/(m²·K)]."""

    def __init__(
        self,
        rom: Any,
        spec: Any,
        *,
        h: ArrayLike,
        dt_s: float = 10.0,
        load_scale: tuple[float, float] = (1.0, 1.0),
        settings: FilterSettings | None = None,
        offsets_c: ArrayLike | None = None,
    ) -> None:
        self.rom = rom
        self.spec = spec
        self.h = np.asarray(h, dtype=np.float64).copy()
        self.dt_s = float(dt_s)
        self.load_scale = (float(load_scale[0]), float(load_scale[1]))
        self.settings = settings or FilterSettings()
        self._noise = self.settings.noise
        self.offsets_c = None if offsets_c is None else np.asarray(offsets_c, dtype=np.float64)
        st = self.settings
        self._book: SnapshotBook[StateSnapshot] = SnapshotBook(
            keep_s=st.keep_s, every_s=st.snapshot_every_s, recent_steps=st.recent_steps, dt_s=self.dt_s
        )
        self._filter: StateEstimator | None = None
        self._nis = NisTrack(st.nis_window, st.converge_nis_samples, keep=max(1, int(st.keep_s / self.dt_s)))
        self._t: float | None = None
        self._inputs: _Inputs | None = None
        # a run of steps without a measurement update (open loop): since when [s], and whether it was long
        # enough (> max_gap_s) that windows wait for the convergence test on data again (``ready_at``)
        self._gate = ConvergenceGate(st.max_gap_s)
        self.started_at: float | None = None
        self.last_restart: tuple[float, str] | None = None  # [s] and why the state last restarted
        self.steps = 0
        sensors = np.asarray(rom.sensors)
        # the unknown offsets' share of the state's error (in ``view().cov``; service.estimate.offsetbias)
        self._bias = OffsetBias(sensors.shape[1], sensors.shape[0])
        self._faults = FaultWatch.of(self.settings.faults, sensors.shape[0], self.settings.noise, self._bias)

    # --- state ----------------------------------------------------------------------------------------
    @property
    def converged_at(self) -> float | None:
        """[s] the first converged sample since the (re)start (None: not yet)."""
        return self._gate.converged_at

    @property
    def reacquired_at(self) -> float | None:
        """[s] the state passed the test again after an open-loop run (None: not since the (re)start)."""
        return self._gate.reacquired_at

    @property
    def high_since(self) -> float | None:
        """[s] the NIS window "high" since (None: not high)."""
        return self._nis.high_since

    @property
    def initialized(self) -> bool:
        return self._filter is not None

    @property
    def t(self) -> float:
        if self._t is None:
            raise LiveStateError("the live state has not been initialised (no sample yet)")
        return self._t

    @property
    def estimator(self) -> StateEstimator:
        if self._filter is None:
            raise LiveStateError("the live state has not been initialised (no sample yet)")
        return self._filter

    def initialize(
        self,
        t: float,
        inputs: tuple[float, float, float],
        temps_c: ArrayLike | None = None,
        usable: ArrayLike | None = None,
        *,
        reason: str = "start",
    ) -> SampleUpdate:
        """Start at ``t`` [s] from the wide prior at the ambient (``inputs`` = ambient [°C], speed [rpm],
        torque [N·m]), then update with the sample's temperatures (32,) [°C] and usable mask, if given;
        ``reason`` why (``SampleUpdate.reason``, ``last_restart``)."""
        ambient = float(inputs[0])
        if not all(math.isfinite(float(x)) for x in inputs):
            raise LiveStateError(
                f"initialize: ambient, speed and torque must be finite (CAN down?), got {inputs}"
            )
        sig = self.settings.prior_sigma_c
        if self.settings.prior == "heated":
            prior = heated_prior(self.rom, ambient_c=ambient, sigma_uniform_c=sig)
        else:
            prior = wide_prior(self.rom, ambient_c=ambient, sigma_uniform_c=sig, sigma_shape_c=sig)
        self._filter = StateEstimator(self.rom, prior, noise=self._noise, offsets_c=self.offsets_c)
        self._bias.restart()
        self._faults.restart()
        self._t = float(t)
        self._inputs = _Inputs(*(float(x) for x in inputs))
        self._nis.restart()
        self._gate.restart()
        self.started_at = float(t)
        self._book.clear()
        self.last_restart = (float(t), reason)
        return self._after_step(0, self._measure(temps_c, usable), restarted=True, reason=reason)

    def checkpoint(self, model_version: str) -> LiveCheckpoint:
        """The state now as a ``LiveCheckpoint`` (``service.contracts.checkpoint``) of ``model_version``."""
        est, inp = self.estimator.estimate, self._inputs
        assert inp is not None
        return LiveCheckpoint(
            t=self.t,
            model_version=model_version,
            converged=not self._gate.initial,
            inputs=(inp.ambient_c, inp.speed_rpm, inp.torque_nm),
            mean=est.mean.copy(),
            cov=est.cov.copy(),
            cross=est.cross.copy(),
            bias_s=self._bias.s.copy(),
            bias_m=self._bias.m.copy(),
            param_std=self._noise.param_std(),
        )

    def resume(self, cp: LiveCheckpoint, model_version: str) -> None:
        """Continue from a stored checkpoint (after a restart) instead of the prior: the next ``push``
        predicts across the gap with the checkpoint's inputs held (a gap over ``max_gap_s`` starts from the
        prior as ever). A converged checkpoint is converged from its time on (the served values need no new
        convergence), but identification windows wait, as after an open-loop run, until the state has passed
        the convergence test on data after the restart (``ready_at``): a window may not start at the
        checkpoint, before the first sample the new process has (the speed map's prior would then overlap the
        restored fit's window and fall back to the cold prior: measured, H1 and H5 at the box bound for an
        hour after a restart). Its cross-covariance is rescaled from the checkpoint's considered 1σ to the
        current ones (``set_h`` before ``resume`` sets them), so the joint covariance stays positive
        semi-definite. ``CheckpointError`` if it is another model's or another size (the state is then left
        as it was)."""
        cp.check_for(model_version, int(self.rom.k0.shape[0]), self._bias.n)
        estimate = Estimate(mean=cp.mean.copy(), cov=cp.cov.copy(), cross=cp.cross.copy())
        if cp.param_std is not None:  # the cross goes with the checkpoint's 1σ: rescale it to the H set now
            estimate = rescale_cross(estimate, cp.param_std, self._noise.param_std())
        self._filter = StateEstimator(self.rom, estimate, noise=self._noise, offsets_c=self.offsets_c)
        self._bias.s, self._bias.m = cp.bias_s.copy(), cp.bias_m.copy()
        self._t = float(cp.t)
        self._inputs = _Inputs(*cp.inputs)
        self._nis.restart()
        self._gate.restart(float(cp.t) if cp.converged else None)
        self.started_at = float(cp.t)
        self._book.clear()
        self._book.keep(self._snapshot(), force=True)

    def set_h(
        self,
        h: ArrayLike,
        load_scale: tuple[float, float] | None = None,
        *,
        h_rel: ArrayLike | None = None,
        **_: Any,
    ) -> None:
        """Use H (7,) [W/(m²·K)] (and bearing-heat scales) from the next step on; ``h_rel`` (scalar or 7)
        the relative 1σ of these H (e.g. from the identification's CI: σ(log H)), the filter's considered
        H error from now on (clipped to 0.05–1; None: unchanged). Extra keywords of ``LiveModel.set_h``
        such as ``stepper`` are accepted and ignored."""
        arr = np.asarray(h, dtype=np.float64)
        if arr.shape != (7,) or not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
            raise LiveStateError(f"set_h: expected 7 finite H > 0 W/(m²·K), got {arr!r}")
        self.h = arr.copy()
        if load_scale is not None:
            self.load_scale = (float(load_scale[0]), float(load_scale[1]))
        if h_rel is not None:
            rel = np.broadcast_to(np.asarray(h_rel, dtype=np.float64), (7,))
            if not np.all(np.isfinite(rel)):
                raise LiveStateError(f"set_h: h_rel must be finite, got {h_rel!r}")
            self._noise = replace(self._noise, h_rel=tuple(float(x) for x in np.clip(rel, 0.05, 1.0)))
            if self._filter is not None:  # rescales the cross-covariance with the considered H errors
                self._filter.set_noise(self._noise)

    def set_offsets(self, offsets_c: ArrayLike | None, sd_c: ArrayLike | None = None) -> None:
        """Per-channel offsets (32,) [°C] subtracted before each update (a new calibration) and the 1σ (32,)
        [°C] of what is still unknown of them (``OffsetCalibrator.offset_sd``: 0.17 °C before a baseline,
        ~0.02 °C after). That remainder is a constant error per channel; the filter takes its RMS as extra
        white measurement noise (σ² = ``noise.sigma_meas_c``² + RMS(sd)²), so unknown offsets widen the
        update instead of making the innovations inconsistent (None: unchanged)."""
        offsets = None if offsets_c is None else np.asarray(offsets_c, dtype=np.float64)
        self.offsets_c = offsets
        if self._filter is not None:
            self._filter.offsets_c = np.zeros(32) if offsets is None else offsets.copy()
        if sd_c is not None:
            sd = np.asarray(sd_c, dtype=np.float64)
            if sd.shape == (self._bias.n,):
                self._bias.set_sd(sd)
            sigma = _with_rms(self.settings.noise.sigma_meas_c, sd[np.isfinite(sd)])
            self._noise = replace(self._noise, sigma_meas_c=sigma)
            if self._filter is not None:
                self._filter.set_noise(self._noise)

    def push(
        self,
        t: float,
        *,
        ambient_c: float,
        speed_rpm: float,
        torque_nm: float,
        temps_c: ArrayLike | None = None,
        usable: ArrayLike | None = None,
    ) -> SampleUpdate:
        """Advance to sample time ``t`` [s] with the previous sample's inputs held, then correct with this
        sample's temperatures (32,) [°C] over the ``usable`` channels (True = quality OK; None: all finite).

        The state moves on a fixed grid of ``dt_s``: ``round((t − t_state)/dt_s)`` steps, predictions only
        except the last, which is updated. A gap over ``max_gap_s`` restarts from the wide prior, and so does
        a belief that stopped being a distribution (``CovarianceError``: never served as converged).
        Non-finite inputs hold the last valid ones.
        """
        if self._filter is None or self._t is None or self._inputs is None:
            raise LiveStateError("initialize() the live state before pushing samples")
        new = _held(self._inputs, (ambient_c, speed_rpm, torque_nm))
        n = int(np.floor((float(t) - self._t) / self.dt_s + 0.5))
        inputs = (new.ambient_c, new.speed_rpm, new.torque_nm)
        if n * self.dt_s > self.settings.max_gap_s:
            return self.initialize(float(t), inputs, temps_c, usable, reason="gap")
        if n <= 0:
            self._inputs = new
            return SampleUpdate(self._t, 0, 0.0, 0, self._nis.window.verdict())
        step = self._step_input(self._inputs)
        a = self._filter.transition(step.h, step.dt_s).a
        try:
            for _ in range(n - 1):
                self._filter.predict(step)
                self._bias.predict(a)
                self._t += self.dt_s
                self._book.keep(self._snapshot())
            self._filter.predict(step)
            self._bias.predict(a)
            self._t += self.dt_s
            self._inputs = new
            res = self._measure(temps_c, usable)
        except CovarianceError as err:
            # the belief is no longer a distribution: never serve it (nor its convergence); start again
            return self.initialize(float(t), inputs, temps_c, usable, reason=f"covariance: {err}")
        if self._prediction_lost(res):
            # the open-loop prediction is out of its own band (CAN was down too, say: the inputs held were
            # not the machine's): restart from the prior on these data rather than bend the unobserved field
            # (the shaft) by a correction the covariance does not cover
            return self.initialize(float(t), inputs, temps_c, usable, reason="prediction lost")
        return self._after_step(n, res)

    def mark(self, t: float) -> StateSnapshot | None:
        """Keep the estimate of the latest step at or before ``t`` [s] as a snapshot (a window can start
        there); called at a condition change, whose start lies up to the hold time in the past. None when
        the state has none that old (it started after ``t``: a window cannot start there; never an error)."""
        return self._book.mark(t)

    # --- queries --------------------------------------------------------------------------------------
    def field_now(self) -> StateSnapshot:
        """The current estimate (mean, covariance, field)."""
        return self._snapshot()

    def sensors_now(self) -> Array:
        """Predicted temperatures (32,) [°C] at the sensors, in the readings' frame (offsets added back)."""
        mean = self.estimator.sensors_mean()
        return mean if self.offsets_c is None else mean + self.offsets_c

    def sensors_std_now(self) -> Array:
        """1σ (32,) [°C] of the sensors' true temperatures: the state's part √diag(C·P·Cᵀ) and, in quadrature,
        the model's error at the sensors outside the reduced state (``NoiseModel.sigma_model_c``: mesh and
        reduction), not the DAQ's noise."""
        state = self.estimator.sensors_std()
        return np.asarray(np.sqrt(state**2 + self.settings.noise.sigma_model_c**2))

    def field_std_now(self, nodes: ArrayLike | None = None) -> Array:
        """1σ [°C] of the field now at all nodes (N,) or at ``nodes``."""
        return self.estimator.field_std(nodes)

    def field_at(self, t: float) -> StateSnapshot:
        """The latest snapshot at or before ``t`` [s], up to half a step later (sample-time jitter)."""
        return self._book.at(t)

    def covariance_at(self, t: float) -> Array:
        """The covariance (r, r) [°C²] of the snapshot ``field_at(t)``: ``identify(start_cov=...)``."""
        return np.array(self.field_at(t).cov)

    def convergence(self) -> Convergence:
        """The convergence test now (``model.estimator.convergence``): covariance bounds, NIS window."""
        st = self.settings
        return convergence(
            self.rom,
            self.estimator.estimate,
            self._nis.gate,
            sensor_std_bound_c=st.sensor_std_bound_c,
            field_rms_bound_c=st.field_rms_bound_c,
        )

    def ready_at(self) -> float | None:
        """Earliest window start [s] allowed: the first converged sample since the (re)start, or after the
        last open-loop run longer than ``max_gap_s`` the first sample the state passed the convergence test
        on data again (None: not yet). An identification window never starts on a state that ran open loop
        (a DAQ outage): its start field would be the open-loop prediction, and the fit would bend H to it."""
        return self._gate.ready_at()

    @property
    def reacquiring(self) -> bool:
        """The state ran open loop for longer than ``max_gap_s`` and has not passed the test on data again."""
        return self._gate.reacquiring

    def view(self) -> FilterView:
        """An immutable copy of the state now for readers on other threads (raises before ``initialize``)."""
        est, inp = self.estimator.estimate, self._inputs
        assert inp is not None and self.started_at is not None
        reason = self._gate.reason()
        offset_cov = self._bias.extra_cov()
        return FilterView(
            t=self.t,
            mean=_frozen(est.mean.copy()),
            cov=_frozen(est.cov + offset_cov),  # with the unknown offsets' share
            basis=self.rom.basis,
            sensor_rows=np.asarray(self.rom.sensors),
            sigma_model_c=float(self.settings.noise.sigma_model_c),
            h=tuple(float(x) for x in self.h),
            load_scale=self.load_scale,
            inputs=(inp.ambient_c, inp.speed_rpm, inp.torque_nm),
            started_at=self.started_at,
            converged_at=self.converged_at,
            reason=reason,
            **self._nis.view_fields(),
            inconsistent_after_s=self.settings.inconsistent_after_s,
            offset_cov=_frozen(offset_cov),
            sensor_faults=self.sensor_faults(),
        )

    def suspect_channels(self, t_from: float, t_to: float) -> NDArray[np.bool_]:
        """Channels (32,) whose data in [t_from, t_to] [s] an identification window must leave out: stuck
        or drifting now or then (``FaultWatch.suspect``)."""
        return self._faults.suspect(t_from, t_to)

    def sensor_faults(self) -> tuple[SensorFault, ...]:
        """The channels left out of the updates now, stuck or drifting (``service.estimate.sensorfaults``)."""
        return self._faults.active()

    # --- internals ------------------------------------------------------------------------------------
    def _measure(self, temps_c: ArrayLike | None, mask: ArrayLike | None) -> StepResult | None:
        if temps_c is None:
            return None
        est = self.estimator
        y = np.asarray(temps_c, dtype=np.float64)
        if y.shape != (self._bias.n,):
            return est.update(y, mask)  # the estimator names the bad shape
        ok = usable_channels(y - est.offsets_c, mask)
        use = self._faults.usable(ok)
        if use.any():
            sensors = np.asarray(self.rom.sensors)
            gain = kalman_gain(est.estimate.cov, sensors, use, est.noise.r_var)
            self._bias.update(gain, sensors, use)
        res = est.update(y, use)
        if self._t is not None and self.converged_at is not None:
            self._faults.observe(self._t, y, ok, res, est.offsets_c)
        return res

    def _after_step(
        self, n: int, res: StepResult | None, *, restarted: bool = False, reason: str = ""
    ) -> SampleUpdate:
        assert self._t is not None
        nis, dof = (0.0, 0) if res is None else (res.nis, res.dof)
        self._track_blind(n, dof)
        verdict = self._nis.push(self._t, nis, dof)
        newly = False
        if self._gate.testing(dof):
            self._gate.last = self.convergence()
            newly = self._gate.last.converged
        if newly:
            self._gate.passed(self._t)
        self._book.keep(self._snapshot(), force=newly)  # the first window start allowed is always kept
        self.steps += n
        return SampleUpdate(self._t, n, nis, dof, verdict, restarted, reason, self._faults.take_changes())

    def _prediction_lost(self, res: StepResult | None) -> bool:
        """The first update after an open-loop run longer than ``max_gap_s`` has an improbable NIS."""
        if res is None or not self._gate.after_open_loop(res.dof):
            return False
        return bool(res.nis > chi2.isf(self.settings.reacquire_restart_p, res.dof))

    def _track_blind(self, n: int, dof: int) -> None:
        """Follow runs of steps without a measurement update (``ConvergenceGate.track_blind``)."""
        assert self._t is not None
        if self._gate.track_blind(self._t, n, self.dt_s, dof):
            self._nis.regate()

    def _snapshot(self) -> StateSnapshot:
        est = self.estimator.estimate
        initial = self._gate.initial
        return StateSnapshot(self.t, est.mean, est.cov, initial, self.rom.basis)

    def _step_input(self, inp: _Inputs) -> StepInput:
        qf, qr = _bearing_heat(self.spec, inp, self.load_scale)
        return StepInput(self.h, inp.ambient_c, qf, qr, self.dt_s)
