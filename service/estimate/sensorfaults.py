"""Sensor faults the DAQ does not flag: a stuck or drifting channel, found from the filter's checks (pure).

The DAQ flags an open circuit or a value out of range (quality not ok: the channel is left out of the update
already). A channel that freezes at its last value, or drifts (a thermocouple or its cold junction ageing,
+0.5 °C/h say), keeps quality ok and would bend the live field towards it. :class:`FaultMonitor` watches
each channel's reading against what the filter predicted for it before the update
(``model.estimator.StepResult``: ``predicted_c`` and ``predicted_std_c`` = √diag(S), for every channel,
used or not) and decides which channels the filter may use:

- **stuck**: the raw reading's peak-to-peak over the last ``stuck_window`` samples is within
  ``stuck_band_c`` although the DAQ's noise alone (``noise_c``, the filter's σ) would spread it by far more,
  or the prediction moved by more than ``stuck_min_change_c``. Recovers once the reading moves again
  (peak-to-peak over the last ``recover_window`` samples above the band) and agrees with the prediction.
- **drift**: a two-sided CUSUM (Page 1954; Basseville & Nikiforov 1993, 2.2) on the channel's normalised
  innovation z = (y − ŷ⁻)/√S less its reference mean (an average over the first ``reference_samples``, then
  an exponential one with time constant ``reference_tau_samples``: a constant offset the baseline did not
  remove is not a drift), with allowance ``cusum_k`` and threshold ``cusum_h`` (σ·samples). Recovers once
  the last ``recover_window`` z (from the prediction of a state that no longer sees the channel) have a mean
  within ``recover_z`` of the reference and an RMS within ``recover_rms``.

At most ``max_excluded`` channels are excluded at once: many channels leaving together is the model's
problem (the NIS verdict says so), not the sensors'. A channel the DAQ flags is not judged (its fault is
known); a channel that recovers starts from a fresh CUSUM and a window that only holds readings after the
recovery.

``observe(...)`` returns the :class:`FaultChange` s of that sample (detected, recovered); ``active()`` the
faults now, ``excluded()`` the mask to take out of the filter's update. The caller widens the state for a
detected channel (``FilteredState.forget_channel``: what its readings bent so far becomes an uncertainty).

Errors::

    SensorFaultError(ServiceError, ValueError)   bad arrays (shape) or settings, the field named
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.contracts.sensorfault import FaultKind, SensorFault
from service.errors import ServiceError

__all__ = [
    "FaultChange",
    "FaultKind",
    "FaultMonitor",
    "FaultMonitorSettings",
    "SensorFault",
    "SensorFaultError",
    "fault_lines",
]

Array = NDArray[np.float64]


class SensorFaultError(ServiceError, ValueError):
    """Bad input to the fault monitor; the message names the field."""


@dataclass(frozen=True, kw_only=True)
class FaultMonitorSettings:
    """See the module docstring; samples are the live state's (10 s by default)."""

    stuck_window: int = 30  # samples whose raw readings must stay within the band (5 min at 10 s)
    stuck_band_c: float = 0.005  # [°C] peak-to-peak of a frozen reading (a DAQ's quantum is 0.01 °C)
    stuck_min_change_c: float = 0.1  # [°C] the prediction's move over the window that a live sensor shows
    cusum_k: float = 0.5  # [σ] allowance per sample
    cusum_h: float = 50.0  # [σ·samples] alarm threshold (a stale H drove clean channels to 32 on the plant)
    reference_samples: int = 60  # the reference mean: the plain average over the first samples (10 min)
    reference_tau_samples: float = 2160.0  # then an exponential average with this time constant (6 h)
    recover_window: int = 30  # samples (5 min) judged for a recovery
    recover_z: float = 0.5  # |mean z − reference| within this [σ]
    recover_rms: float = 1.5  # RMS of z − reference within this [σ]
    max_excluded: int = 3  # channels excluded at once at most
    # a CUSUM above this fraction of cusum_h: the channel's data are suspect (identification windows leave it
    # out; the live state still uses it), at most max_excluded such channels, the highest first
    suspect_cusum_frac: float = 0.5

    def __post_init__(self) -> None:
        for name in ("stuck_window", "reference_samples", "recover_window"):
            if getattr(self, name) < 2:
                raise SensorFaultError(f"{name}: must be >= 2 samples, got {getattr(self, name)}")
        if not 0.0 < self.suspect_cusum_frac <= 1.0:
            raise SensorFaultError(f"suspect_cusum_frac: must be in (0, 1], got {self.suspect_cusum_frac}")
        for name in ("stuck_band_c", "stuck_min_change_c", "cusum_k", "cusum_h", "recover_z", "recover_rms"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise SensorFaultError(f"{name}: must be finite and > 0, got {v}")
        if not self.reference_tau_samples >= 1.0:
            raise SensorFaultError(f"reference_tau_samples: must be >= 1, got {self.reference_tau_samples}")
        if self.max_excluded < 0:
            raise SensorFaultError(f"max_excluded: must be >= 0, got {self.max_excluded}")


@dataclass(frozen=True)
class FaultChange:
    """One change at sample time ``t`` [s]: ``fault`` detected (``recovered`` False) or recovered, and
    ``bias_c`` [°C] the size of what the channel's readings are off now (the detection's evidence: the
    drift's innovation mean, or the frozen reading against the prediction; 0 for a recovery)."""

    t: float
    fault: SensorFault
    recovered: bool = False
    bias_c: float = 0.0


@dataclass
class FaultMonitor:
    """Per-channel stuck and drift tests (module docstring) for ``n_channels`` sensors named ``channels``
    (1-based numbers; default 1..n), with the filter's measurement noise 1σ ``noise_c`` [°C]. Vectorised
    over the channels: ~0.1 ms a sample."""

    n_channels: int = 32
    noise_c: float = 0.15
    settings: FaultMonitorSettings = field(default_factory=FaultMonitorSettings)
    channels: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not self.channels:
            self.channels = tuple(range(1, self.n_channels + 1))
        if len(self.channels) != self.n_channels:
            raise SensorFaultError(f"channels: expected {self.n_channels} numbers, got {len(self.channels)}")
        st, n = self.settings, self.n_channels
        self._keep = max(st.stuck_window, st.recover_window)
        # ring buffers (keep, n) of the raw readings, the predictions and z − reference; ``_fill`` samples per
        # channel since its window last restarted (a flagged sample, a detection, a recovery)
        self._raw = np.full((self._keep, n), np.nan)
        self._pred = np.full((self._keep, n), np.nan)
        self._dz = np.full((self._keep, n), np.nan)
        self._pos = 0
        self._fill = np.zeros(n, dtype=np.int64)
        self._n_ref = np.zeros(n, dtype=np.int64)
        self._ref = np.zeros(n)
        self._hi = np.zeros(n)
        self._lo = np.zeros(n)
        self._faults: list[SensorFault | None] = [None] * n
        # per fault found: (index, suspect from [s], until [s]; None: still out), for the data windows
        self._spans: list[tuple[int, float, float | None]] = []
        self._last_t: float | None = None
        self._period = 10.0

    # --- queries --------------------------------------------------------------------------------------
    def active(self) -> tuple[SensorFault, ...]:
        """The faults now, by channel."""
        return tuple(f for f in self._faults if f is not None)

    def excluded(self) -> NDArray[np.bool_]:
        """True where the filter must not use the channel (n,)."""
        return np.array([f is not None for f in self._faults], dtype=bool)

    def suspect(self, t_from: float, t_to: float) -> NDArray[np.bool_]:
        """Channels (n,) whose data in [t_from, t_to] [s] are suspect: out now, or a fault found overlaps
        the span (a stuck channel from its frozen window's start; a drift from any time before it was found,
        as its start is unknown), or a CUSUM risen past ``suspect_cusum_frac`` of its threshold without an
        alarm yet (a drift not yet found: its start is unknown too). An identification window leaves them out
        entirely."""
        out = self.excluded()
        for i, lo, hi in self._spans:
            if t_to >= lo and (hi is None or t_from <= hi):
                out[i] = True
        st = self.settings
        level = np.where(out, 0.0, np.maximum(self._hi, self._lo))
        rising = np.flatnonzero(level >= st.suspect_cusum_frac * st.cusum_h)
        out[rising[np.argsort(-level[rising])][: st.max_excluded]] = True
        return out

    def restart(self) -> None:
        """The filter restarted from its prior: its first predictions say nothing of the sensors. The
        CUSUMs start again from 0; the faults found and the reference means are kept."""
        self._hi[:] = 0.0
        self._lo[:] = 0.0

    # --- the test -------------------------------------------------------------------------------------
    def observe(
        self,
        t: float,
        raw_c: ArrayLike,
        ok: ArrayLike,
        predicted_c: ArrayLike,
        predicted_std_c: ArrayLike,
        offsets_c: ArrayLike | None = None,
    ) -> list[FaultChange]:
        """One sample at ``t`` [s]: the raw readings (n,) [°C], the DAQ's ok mask (n,), the filter's
        prediction before the update (n,) [°C, offset-corrected frame] and its 1σ √diag(S) (n,) [°C], the
        offsets subtracted before the update (n,) [°C; None: none]."""
        n, st = self.n_channels, self.settings
        if self._last_t is not None and t > self._last_t:
            self._period = float(t) - self._last_t
        self._last_t = float(t)
        y = _vector("raw_c", raw_c, n)
        good = np.asarray(ok, dtype=bool)
        if good.shape != (n,):
            raise SensorFaultError(f"ok: expected shape ({n},), got {good.shape}")
        pred = _vector("predicted_c", predicted_c, n)
        sd = _vector("predicted_std_c", predicted_std_c, n)
        off = np.zeros(n) if offsets_c is None else _vector("offsets_c", offsets_c, n)
        nu = y - off - pred
        with np.errstate(divide="ignore", invalid="ignore"):
            z = nu / sd
        valid = good & np.isfinite(y) & np.isfinite(pred) & np.isfinite(z) & (sd > 0.0)
        dz = np.where(valid, z - self._ref, np.nan)
        row = self._pos
        self._raw[row] = np.where(valid, y, np.nan)
        self._pred[row] = np.where(valid, pred, np.nan)
        self._dz[row] = dz
        self._pos = (row + 1) % self._keep
        # a flagged sample (the DAQ's own fault, known) restarts the channel's windows
        self._fill = np.where(valid, np.minimum(self._fill + 1, self._keep), 0)
        excluded = self.excluded()
        healthy = valid & ~excluded
        self._learn(healthy, z)
        acc = healthy & (self._n_ref > st.reference_samples)  # the reference is known: accumulate
        self._hi = np.where(acc, np.maximum(0.0, self._hi + dz - st.cusum_k), self._hi)
        self._lo = np.where(acc, np.maximum(0.0, self._lo - dz - st.cusum_k), self._lo)
        changes = self._recoveries(t, valid & excluded)
        changes += self._detections(t, healthy, nu, sd)
        return changes

    # --- internals ------------------------------------------------------------------------------------
    def _window(self, buf: Array, w: int) -> Array:
        """The last ``w`` rows of ``buf`` (w, n), oldest first."""
        idx = (self._pos - w + np.arange(w)) % self._keep
        return buf[idx]

    def _dt_s(self) -> float:
        """The sample period [s] as seen (the last two observations; 10 s before)."""
        return self._period

    def _learn(self, healthy: NDArray[np.bool_], z: Array) -> None:
        st = self.settings
        self._n_ref = np.where(healthy, self._n_ref + 1, self._n_ref)
        w = np.where(self._n_ref <= st.reference_samples, 1.0 / np.maximum(self._n_ref, 1), 0.0)
        w = np.where(self._n_ref > st.reference_samples, 1.0 / st.reference_tau_samples, w)
        self._ref = np.where(healthy, self._ref + w * (np.nan_to_num(z) - self._ref), self._ref)

    def _detections(self, t: float, healthy: NDArray[np.bool_], nu: Array, sd: Array) -> list[FaultChange]:
        st = self.settings
        ws = st.stuck_window
        raw = self._window(self._raw, ws)
        pred = self._window(self._pred, ws)
        full = healthy & (self._fill >= ws)  # their last ws rows are all valid (NaN elsewhere: masked)
        with np.errstate(invalid="ignore"):
            ptp = np.where(full, raw.max(axis=0) - raw.min(axis=0), np.inf)
            moved = np.where(full, pred.max(axis=0) - pred.min(axis=0), 0.0)
        noise_shows = self.noise_c >= 10.0 * st.stuck_band_c
        stuck = full & (ptp <= st.stuck_band_c) & (noise_shows | (moved >= st.stuck_min_change_c))
        drift = healthy & ~stuck & (np.maximum(self._hi, self._lo) > st.cusum_h)
        room = st.max_excluded - int(self.excluded().sum())
        out: list[FaultChange] = []
        for i in np.flatnonzero(stuck | drift)[: max(room, 0)]:
            if drift[i] and self._fill[i] >= 6:  # a frozen reading the model ran away from: stuck, not drift
                recent = self._window(self._raw, 6)[:, i]  # the last minute: noise alone never repeats
                stuck[i] = float(recent.max() - recent.min()) <= st.stuck_band_c
            if stuck[i]:
                n_flat = ws if self._fill[i] >= ws and not drift[i] else 6
                last = self._raw[(self._pos - 1) % self._keep, i]
                detail = (
                    f"reading frozen at {last:.2f} °C for {n_flat}+ samples (peak-to-peak ≤ "
                    f"{st.stuck_band_c:.3f} °C) while the noise ({self.noise_c:.2f} °C) or the model should "
                    "move it"
                )
                out.append(self._detect(t, int(i), FaultKind.STUCK, detail, abs(float(nu[i]))))
                continue
            w = int(min(self._fill[i], st.recover_window))
            mean_dz = float(np.mean(self._window(self._dz, max(w, 1))[:, i]))
            bias = abs(mean_dz) * float(sd[i])
            sign = "+" if self._hi[i] >= self._lo[i] else "−"
            detail = (
                f"drifting {sign}: CUSUM of the normalised innovation {max(self._hi[i], self._lo[i]):.0f} "
                f"over {st.cusum_h:.0f} (recent mean {mean_dz:+.1f} σ off its reference)"
            )
            out.append(self._detect(t, int(i), FaultKind.DRIFT, detail, bias))
        return out

    def _detect(self, t: float, i: int, kind: FaultKind, detail: str, seen_c: float) -> FaultChange:
        """``seen_c`` [°C] the error the innovations show; the filter, using the channel, followed it part
        of the way, so the channel is off by more: twice that is the bias charged (``FaultChange.bias_c``)."""
        fault = SensorFault(self.channels[i], i, kind, float(t), detail)
        self._faults[i] = fault
        ws = self.settings.stuck_window
        start = float(t) - (ws + 1) * self._dt_s() if kind is FaultKind.STUCK else -math.inf
        self._spans = [*self._spans[-63:], (i, start, None)]
        self._fill[i] = 0
        return FaultChange(t, fault, bias_c=2.0 * float(seen_c))

    def _recoveries(self, t: float, watched: NDArray[np.bool_]) -> list[FaultChange]:
        st = self.settings
        w = st.recover_window
        cand = watched & (self._fill >= w)
        if not cand.any():
            return []
        raw = self._window(self._raw, w)
        dz = self._window(self._dz, w)
        out: list[FaultChange] = []
        for i in np.flatnonzero(cand):
            moves = float(np.max(raw[:, i]) - np.min(raw[:, i])) > st.stuck_band_c
            mean, rms = float(np.mean(dz[:, i])), float(np.sqrt(np.mean(dz[:, i] ** 2)))
            if moves and abs(mean) <= st.recover_z and rms <= st.recover_rms:
                fault = self._faults[i]
                assert fault is not None
                self._faults[i] = None
                self._spans = [
                    (j, lo, float(t) if j == i and hi is None else hi) for j, lo, hi in self._spans
                ]
                self._hi[i] = self._lo[i] = 0.0
                self._fill[i] = 0
                out.append(FaultChange(t, fault, recovered=True))
        return out


def fault_lines(changes: Iterable[FaultChange]) -> list[str]:
    """The log's line per change: channel, kind, since when (UTC) and why; or that it is taken back."""
    out = []
    for ch in changes:
        f = ch.fault
        since = datetime.fromtimestamp(f.since_t, tz=UTC).isoformat(timespec="seconds")
        if ch.recovered:
            at = datetime.fromtimestamp(ch.t, tz=UTC).isoformat(timespec="seconds")
            out.append(
                f"sensor channel {f.channel} taken back into the live state at {at}: its readings agree "
                f"with the model again (left out as {f.kind.value} since {since})"
            )
        else:
            out.append(
                f"sensor channel {f.channel} left out of the live state as {f.kind.value} since {since}: "
                f"{f.detail}; the growth's CI carries what it bent (~{ch.bias_c:.2f} °C)"
            )
    return out


def _vector(name: str, values: ArrayLike, n: int) -> Array:
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (n,):
        raise SensorFaultError(f"{name}: expected shape ({n},), got {arr.shape}")
    return arr
