"""The condition terms of the served thermal growth (``service.estimate.growth``), from what a published view
holds: the H covariance of the identification that serves, the live state's belief, and a small thread-safe
cache of the terms per key (docs/design/growth.md, "Serving"). Pure computation: no I/O, no clock; the lock
only guards the cache, which the API threads and the shell's worker threads share.

The live field's uncertainty comes through ONE function, :func:`live_belief`: the filtered live state's
reduced mean and covariance (issue 16), which already hold the considered H error.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Hashable
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import ArrayLike

from model.growth import Z95
from service.estimate.growth import ConditionTerms, FieldBelief, GrowthContext, condition_terms, h_cov_from_ci
from service.estimate.state import FilterView

if TYPE_CHECKING:
    from model.geometry import SpindleSpec
    from model.hmap import Family

__all__ = [
    "DT_S",
    "TERMS_KEPT",
    "UNKNOWN_CI_FACTOR",
    "CiRecord",
    "TermsCache",
    "guessed_h_covariance",
    "h_covariance",
    "held_terms",
    "live_belief",
    "map_h_covariance",
]

DT_S = 10.0  # the live state's step [s]
UNKNOWN_CI_FACTOR = 100.0  # each CI bound capped at H/100 and H·100 (a huge σ)
TERMS_KEPT = 16  # condition terms kept (compact: 78 KiB each on the service mesh, 1.27 MiB in full)


class CiRecord(Protocol):
    """What the H covariance reads of an identification record (``IdentificationRecord``): H and its 95 %
    CI bounds, (7,) W/(m²·K) each."""

    @property
    def h(self) -> ArrayLike: ...

    @property
    def ci95_lo(self) -> ArrayLike: ...

    @property
    def ci95_hi(self) -> ArrayLike: ...


class SpeedMap(Protocol):
    """What the H covariance reads of a speed map (``service.identify.speedmap.SpeedMap``): its family and its
    posterior over the family's parameters θ (mean, covariance)."""

    @property
    def model_family(self) -> Family: ...

    @property
    def mean(self) -> ArrayLike: ...

    @property
    def cov(self) -> ArrayLike: ...


def live_belief(live: FilterView | None) -> FieldBelief:
    """The live field's mean and uncertainty as the growth estimate takes it: the filtered live state's
    reduced mean and covariance (``service.estimate.state``, a Schmidt–Kalman filter whose covariance
    already holds the considered H error: ``includes_h``)."""
    if live is None:
        raise ValueError("view.live: the live state has not started")
    return FieldBelief(state=np.asarray(live.mean), cov=np.asarray(live.cov), includes_h=True)


def h_covariance(rec: CiRecord, h_live: np.ndarray) -> np.ndarray:
    """Σ_H (7, 7) from ``rec``'s 95 % CIs, relative to the H the live state uses (uncorrelated: the stored
    record keeps no correlation). Each bound is capped at H/100 and H·100 (a missing or non-positive one, or
    one of a hopeless H, whose log-H CI can reach 1e-30..1e+60): then σ_H ≈ 2.3·H, linearised."""
    h = np.asarray(rec.h, dtype=float)
    good = np.isfinite(h) & (h > 0)
    h = np.where(good, h, h_live)
    lo, hi = np.asarray(rec.ci95_lo, dtype=float), np.asarray(rec.ci95_hi, dtype=float)
    bad = ~(good & np.isfinite(lo) & np.isfinite(hi) & (lo > 0) & (hi >= lo))
    lo = np.where(bad, 0.0, lo)
    hi = np.where(bad, np.inf, hi)
    lo = np.maximum(lo, h / UNKNOWN_CI_FACTOR)  # a CI in log H can reach 1e-30..1e+60: capped
    hi = np.minimum(hi, h * UNKNOWN_CI_FACTOR)
    cov = h_cov_from_ci(h, np.column_stack([lo, hi]))
    return np.asarray(cov * np.outer(h_live / h, h_live / h))


def guessed_h_covariance(h_live: np.ndarray) -> np.ndarray:
    """Σ_H (7, 7) of H no identification gave (before the first one): each 95 % CI H/100..H·100, the cap of
    ``h_covariance`` (uncorrelated)."""
    h = np.asarray(h_live, dtype=float)
    ci = np.column_stack([h / UNKNOWN_CI_FACTOR, h * UNKNOWN_CI_FACTOR])
    return np.asarray(h_cov_from_ci(h, ci))


def map_h_covariance(m: SpeedMap, speed_rpm: float, ambient_c: float, h_live: np.ndarray) -> np.ndarray:
    """Σ_H (7, 7) in speed-map mode: the map's posterior at ``speed_rpm`` and ``ambient_c`` (the live state's
    held condition, where its H comes from), Σ_lnH = J Σ_θ Jᵀ with J = d ln H/dθ there, so with the
    correlations between the zones that the map fit determined; relative to ``h_live`` and with each σ
    capped as ``h_covariance`` (at ln 100 / 1.96)."""
    fam, theta, cov_theta = m.model_family, np.asarray(m.mean), np.asarray(m.cov)
    speed = [abs(float(speed_rpm))]
    jac = fam.log_h_jacobian(theta, speed, ambient_c)[0]  # (7, p)
    cov_log = jac @ cov_theta @ jac.T
    sd = np.sqrt(np.maximum(np.diag(cov_log), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_log / np.outer(sd, sd)
    h = fam.h_at(theta, speed, ambient_c)[0]
    half = np.minimum(Z95 * sd, np.log(UNKNOWN_CI_FACTOR))  # the cap of h_covariance
    ci = np.column_stack([h * np.exp(-half), h * np.exp(half)])
    out = h_cov_from_ci(h, ci, correlation=corr) * np.outer(h_live / h, h_live / h)
    return np.asarray(out)


def held_terms(
    ctx: GrowthContext,
    spec: SpindleSpec,
    live: FilterView,
    held: tuple[float, float, float] | None,
    rec: CiRecord | None,
    speed_map: SpeedMap | None = None,
) -> ConditionTerms:
    """The terms at the held condition ``held`` (ambient [°C], speed [rpm], torque [N·m]; None: the live
    state's inputs); Σ_H from ``rec``'s CIs (per-condition mode) or, in speed-map mode, from ``speed_map``'s
    band at the live state's speed and ambient (the H the live state uses); before the first identification
    (``rec`` None) the live state's guessed H with the widest band (``guessed_h_covariance``: at rest, with no
    heat input, the growth barely depends on H)."""
    from model.inputs import inputs_from_operation

    ambient, speed, torque = held if held is not None else live.inputs
    inp = inputs_from_operation(spec, dt_s=DT_S, speed_rpm=speed, torque_nm=torque, ambient_c=ambient)
    h = np.asarray(live.h, dtype=float)
    if rec is None:
        cov_h = guessed_h_covariance(h)
    elif speed_map is None:
        cov_h = h_covariance(rec, h)
    else:
        live_ambient, live_speed, _ = live.inputs
        cov_h = map_h_covariance(speed_map, live_speed, live_ambient, h)
    return condition_terms(
        ctx,
        h=h,
        cov_h=cov_h,
        ambient_c=float(inp.ambient_c[0]),
        q_front_w=float(inp.q_front_w[0]),
        q_rear_w=float(inp.q_rear_w[0]),
        load_scale=(float(live.load_scale[0]), float(live.load_scale[1])),
    )


class TermsCache:
    """The condition terms of the last ``TERMS_KEPT`` keys, newest last: in speed-map and combined mode the
    live H follows the map at the speed bin and the rounded ambient, which flip back and forth (noise at a
    bin's edge): each value comes back from here instead of ~0.2 s of eigen-solves. ``claim`` marks one key
    pending (one refresh at a time per key); ``computed`` and ``compute_cpu_s`` count the misses and their
    CPU [s]. A key is computed by one thread at a time: a ``get`` of a key another thread is computing waits
    for that result (``joined`` counts them) instead of computing it again beside it (the shell's refresher
    and every outlet reading the same new view). Thread-safe."""

    def __init__(self, kept: int = TERMS_KEPT) -> None:
        self.kept = kept
        self._lock = threading.Lock()
        self._terms: collections.OrderedDict[Hashable, ConditionTerms] = collections.OrderedDict()
        self._pending: Hashable | None = None
        self._running: dict[Hashable, threading.Event] = {}  # keys being computed: set when done
        self.computed = 0
        self.compute_cpu_s = 0.0
        self.joined = 0

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._terms

    def claim(self, key: Hashable) -> bool:
        """True once per new key not cached (the caller then computes it off the event loop)."""
        with self._lock:
            if key in self._terms or key == self._pending:
                return False
            self._pending = key
            return True

    def get(
        self,
        key: Hashable,
        compute: Callable[[], tuple[ConditionTerms, object]],
        current: Callable[[], object],
    ) -> ConditionTerms:
        """The terms of ``key``: cached, else ``compute()`` (blocking, outside the lock), which returns the
        terms and the growth context they were computed with; they are kept when that context is still
        ``current()`` (a commissioning may have changed the operators meanwhile: then ``clear`` follows).
        While another thread computes ``key``, this one waits for it and takes its result; it computes
        itself when that result was not kept (it failed, or its context was replaced)."""
        joined = False
        while True:
            with self._lock:
                cached = self._terms.get(key)
                if cached is not None:
                    self._terms.move_to_end(key)
                    return cached
                running = self._running.get(key)
                if running is None or joined:
                    done = threading.Event()
                    if running is None:
                        self._running[key] = done
                    break
                self.joined += 1
            running.wait()
            joined = True  # once: its result not kept, compute here (and do not wait again)
        try:
            cpu = time.thread_time()
            terms, ctx = compute()
            with self._lock:
                self.computed += 1
                self.compute_cpu_s += time.thread_time() - cpu
                if ctx is current():
                    self._terms[key] = terms
                    while len(self._terms) > self.kept:
                        self._terms.popitem(last=False)
                if self._pending == key:
                    self._pending = None
            return terms
        finally:
            with self._lock:
                if self._running.get(key) is done:
                    del self._running[key]
            done.set()

    def clear(self) -> None:
        """Forget every key (the operators changed: a commissioning or an absorbed probe reading)."""
        with self._lock:
            self._terms.clear()
            self._pending = None
