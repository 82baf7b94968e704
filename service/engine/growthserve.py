"""Serving the thermal growth at the tool (``GET /compensation``): the shell's side of
``service.estimate.growth`` (docs/design/growth.md, "Serving").

Three stages, by how often their inputs change:

- the growth context (operators of nose axial and radial growth, g·Φ): once per model, ``prepare()``; the
  shell calls it in a thread at ``start()``, otherwise the first request builds it (~0.7 s);
- the condition terms (steady field, modes, horizon functionals, sensor sensitivity): per (identification,
  condition, live H and load scales), ``refresh(view)``; the shell starts it in a thread when a published view
  has a new key (``wants_refresh``), and a request whose key is not ready computes it in its own (API) thread
  (~0.25 s), never on the event loop;
- the estimate: per request, from the latest published ``CoreView`` (dot products).

The live field's uncertainty comes through ONE function, :func:`field_belief`: the filtered live state's
reduced mean and covariance (issue 16), which already hold the considered H error.

The mechanics (docs/commissioning.md, "Commission the growth"): without a commissioning the operators are the
spindle description's (``[mechanics]`` as written) and the policy's ``mechanics_uncalibrated`` rule applies
(``compensation.require_mechanics_calibration``); with one (``mechanics``, restored or set by
``set_mechanics``) the served operators are the calibrated ones and every CI carries the mechanical posterior
(``service.estimate.mechanics``, ``service.estimate.growth.with_mechanics``).

The reference (growth 0: where the controller was zeroed) is a commissioning fact,
``service.estimate.reference.CompensationReference`` (``reference``): stored (``POST
/compensation/reference``, ``chtc commission zero``) and restored at start, else the configured
``compensation.reference_c`` (source "config"), else, if ``compensation.reference_on_first_start`` asks for
it, taken from the first sample at rest in equilibrium and stored (source "first_start"). With none, the
growth is served against a provisional one (the uniform equivalent of the first converged live field, with its
1σ; not stored) and is not usable (reason ``no_reference``).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import itertools
import math
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Protocol

import numpy as np

from model.growth import Z95
from service.contracts.errors import NotReadyError
from service.contracts.growth import GrowthEstimate
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.probe import PROBES_KEPT, ProbeError, ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import (
    CompensationSnapshot,
    ConditionSnapshot,
    IdentificationRecord,
    SectionSnapshot,
)
from service.engine.view import CoreView
from service.estimate.growth import (
    ConditionTerms,
    FieldBelief,
    GrowthContext,
    build_context,
    condition_terms,
    estimate_growth,
    h_cov_from_ci,
    plc_compensation,
    with_mechanics,
)
from service.estimate.growth_section import SectionOperator, build_section, section_displacement_um
from service.estimate.mechanics import ServedMechanicsBasis, served_mechanics_basis
from service.estimate.probe import DEFAULT_GATE_SIGMA, absorb, prior_covariance, prior_mean, replay
from service.estimate.reference import equilibrium_zero, uniform_equivalent
from service.estimate.state import FilterView
from service.serve.policy import CompensationLimits, compensation_verdict

if TYPE_CHECKING:
    from service.identify.speedmap import SpeedMap
    from service.modelload import LoadedModel

__all__ = [
    "GrowthHistory",
    "GrowthServer",
    "field_belief",
    "h_covariance",
    "map_h_covariance",
]

DT_S = 10.0  # the live state's step [s]
UNKNOWN_CI_FACTOR = 100.0  # each CI bound capped at H/100 and H·100 (a huge σ)
TermsKey = tuple[object, ...]
TERMS_KEPT = 16  # condition terms kept (~1 MB each on the service mesh)
REFERENCE_MAX_SD_UM = 0.1  # a zero taken from the live field adds at most this 1σ [µm] to the axial growth
FIELD_KEEP_S = 3 * 3600.0  # the live fields kept for probe readings: the live state's own history (keep_s)
FIELD_KEEP_EVERY_S = 30.0  # one kept every this [s]; a reading takes the nearest


def field_belief(view: CoreView) -> FieldBelief:
    """The live field's mean and uncertainty as the growth estimate takes it: the filtered live state's
    reduced mean and covariance (``service.estimate.state``, a Schmidt–Kalman filter whose covariance
    already holds the considered H error: ``includes_h``)."""
    live = view.live
    if live is None:
        raise ValueError("view.live: the live state has not started")
    return FieldBelief(state=np.asarray(live.mean), cov=np.asarray(live.cov), includes_h=True)


def h_covariance(rec: IdentificationRecord, h_live: np.ndarray) -> np.ndarray:
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


def _default_limits() -> CompensationLimits:
    """The policy's limits for a server built without them (the benches' and the offline history's, which
    judge the growth alone): the settings' ``[compensation]`` defaults (declared there; no environment)
    without the mechanics rule, which has no commissioning to read there."""
    from service.engine.config import compensation_limits
    from service.settings import CompensationSettings

    return dataclasses.replace(
        compensation_limits(CompensationSettings()), require_mechanics_calibration=False
    )


class GrowthServer:
    """See the module docstring. Thread-safe: the API threads and the shell's worker threads call it."""

    def __init__(
        self,
        model: LoadedModel,
        *,
        t_ref_c: float | None = None,
        reference: CompensationReference | None = None,
        reference_on_first_start: bool = False,
        first_start_by: str = "service",
        on_reference: Callable[[CompensationReference], None] | None = None,
        tool_dir: int = -1,
        context: GrowthContext | None = None,  # built already (the bench shares one across runs)
        limits: CompensationLimits | None = None,  # the settings' [compensation] (None: its defaults)
        mechanics: MechanicsCalibration | None = None,  # the stored commissioning (restored)
        mechanics_basis: ServedMechanicsBasis | None = None,  # built already (tests, benches)
        probes: tuple[ProbeMeasurement, ...] = (),  # the stored probe readings (restored), oldest first
        probe_gate_sigma: float = DEFAULT_GATE_SIGMA,
    ) -> None:
        """``reference``: the stored one (restored); else ``t_ref_c`` [°C] (``compensation.reference_c``)
        makes a "config" one; ``reference_on_first_start``: take one from the first sample at rest in
        equilibrium when there is none (``set_by`` ``first_start_by``); ``on_reference`` is told every
        reference taken here (the shell stores it); ``limits`` the settings' [compensation] (None:
        ``_default_limits``)."""
        self.limits = limits if limits is not None else _default_limits()
        self.model = model
        if reference is None and t_ref_c is not None:
            reference = CompensationReference(
                temperature_c=float(t_ref_c),
                sd_c=0.0,
                at=datetime.now(UTC),
                source="config",
                set_by="compensation.reference_c",
            )
        self._reference = reference
        self._first_start = bool(reference_on_first_start)
        self._first_start_by = first_start_by
        self.on_reference = on_reference
        self._provisional: tuple[float, float, datetime] | None = None  # (T, 1σ, at) until a reference exists
        self._ref_lock = threading.RLock()  # API threads and the loop may both take the first-start one
        self.tool_dir = tool_dir
        self._lock = threading.Lock()
        self._ctx: GrowthContext | None = context
        self._error: str | None = None
        # the condition terms of the last TERMS_KEPT keys, newest last: in speed-map and combined mode the
        # live H follows the map at the speed bin and the rounded ambient, which flip back and forth
        # (noise at a bin's edge): each value comes back from here instead of ~0.2 s of eigen-solves
        self._terms: collections.OrderedDict[TermsKey, ConditionTerms] = collections.OrderedDict()
        self._pending: TermsKey | None = None
        self.computed = 0  # condition terms computed (cache misses), and their CPU [s]
        self.compute_cpu_s = 0.0
        self._estimate: tuple[tuple[object, ...], GrowthEstimate] | None = None
        self._section_op: SectionOperator | None = None
        self._section: tuple[tuple[object, ...], np.ndarray] | None = None
        self._commissioning = mechanics
        self._probes: collections.deque[ProbeMeasurement] = collections.deque(probes, maxlen=PROBES_KEPT)
        self.probe_gate_sigma = float(probe_gate_sigma)
        self._fields: collections.deque[tuple[float, np.ndarray, np.ndarray]] = collections.deque(
            maxlen=int(FIELD_KEEP_S / FIELD_KEEP_EVERY_S) + 2
        )
        self._op_phi: np.ndarray | None = None  # the axial mount/α operators on the reduced basis (2, 3, r)
        self._mechanics = self._replayed(mechanics, probes)
        self._mech_basis = mechanics_basis
        self._base_ctx: GrowthContext | None = context  # the described mechanics' context
        if context is not None and self._mechanics is not None:
            self._ctx = None  # calibrated by prepare()

    # --- stage 1
    def prepare(self) -> GrowthContext:
        """The growth context (built once, ~0.7 s; blocking: call it off the event loop). ``NotReadyError``
        naming the cause when the spindle description has no usable mechanics (tried once)."""
        with self._lock:
            if self._ctx is None and self._error is None:
                m = self.model
                try:
                    if self._base_ctx is None:
                        self._base_ctx = build_context(m.spec, m.fe, basis=m.rom.basis)
                    self._ctx = self._calibrated(self._base_ctx, self._mechanics)
                except Exception as err:  # any failure of the optional growth model: served as 503
                    self._error = f"growth model unavailable: {type(err).__name__}: {err}"
            if self._ctx is None:
                raise NotReadyError(self._error or "growth model unavailable")
            return self._ctx

    def _calibrated(self, base: GrowthContext, cal: MechanicsCalibration | None) -> GrowthContext:
        """``base`` with ``cal``'s operators and posterior (the basis built once, ~2 s); ``base`` if None."""
        if cal is None:
            return base
        if self._mech_basis is None:
            self._mech_basis = served_mechanics_basis(self.model.spec, self.model.fe)
        b = self._mech_basis
        return with_mechanics(base, b.operators_at(cal.x), b.jacobian_at(cal.x), cal.covariance)

    @property
    def mechanics(self) -> MechanicsCalibration | None:
        """The mechanics in use: the commissioning updated by the probe readings absorbed since (None: the
        described mechanics, uncalibrated, and no reading absorbed)."""
        return self._mechanics

    @property
    def commissioning(self) -> MechanicsCalibration | None:
        """The commissioning (stored or set), before any probe reading (None: not commissioned)."""
        return self._commissioning

    @staticmethod
    def _prior_calibration(at: datetime) -> MechanicsCalibration:
        """The mechanics before any test (``service.estimate.probe``): a probe reading's start without a
        commissioning; never counts as one (the policy's ``mechanics_uncalibrated`` rule still applies)."""
        cov = prior_covariance()
        return MechanicsCalibration(
            x=(float(prior_mean()[0]), float(prior_mean()[1]), float(prior_mean()[2])),
            cov=tuple(tuple(float(v) for v in row) for row in cov),
            at=at,
            set_by="prior",
            source="prior",
        )

    @staticmethod
    def _posterior(
        base: MechanicsCalibration, x: np.ndarray, cov: np.ndarray, n: int
    ) -> MechanicsCalibration:
        """``base`` with θ ``x`` (clipped to the calibration's range) and Σ ``cov`` after ``n`` readings."""
        xs = (
            float(np.clip(x[0], 0.0, 1.0)),
            float(np.clip(x[1], 0.51, 1.49)),
            float(np.clip(x[2], 0.51, 1.49)),
        )
        report = {**base.report, "probe_readings_absorbed": n}
        return dataclasses.replace(
            base, x=xs, cov=tuple(tuple(float(v) for v in row) for row in cov), report=report
        )

    def _replayed(
        self, cal: MechanicsCalibration | None, probes: tuple[ProbeMeasurement, ...]
    ) -> MechanicsCalibration | None:
        """``cal`` (None: the prior) after the accepted readings measured after it (oldest first); ``cal``
        when there are none."""
        use = sorted((m for m in probes if m.accepted and (cal is None or m.at > cal.at)), key=lambda m: m.at)
        if not use:
            return cal
        base = cal if cal is not None else self._prior_calibration(use[0].at)
        x, cov = replay(base.mean, base.covariance, use)
        return self._posterior(base, x, cov, len(use))

    def mechanics_basis(self) -> ServedMechanicsBasis:
        """The served outputs' mount/α operators (built once, ~2 s; blocking)."""
        with self._lock:
            if self._mech_basis is None:
                self._mech_basis = served_mechanics_basis(self.model.spec, self.model.fe)
            return self._mech_basis

    def set_mechanics(self, cal: MechanicsCalibration) -> None:
        """Serve with ``cal`` from now on (blocking: may build the basis; call it off the event loop): the
        condition terms, which depend on the operators, are recomputed on the next request."""
        self.prepare()
        self.mechanics_basis()
        with self._lock:
            assert self._base_ctx is not None
            self._ctx = self._calibrated(self._base_ctx, cal)
            self._mechanics = cal
            self._commissioning = cal
            self._terms.clear()
            self._pending = None
            self._estimate = None

    # --- probe readings (docs/commissioning.md, "Probe measurements")
    def _keep_field(self, view: CoreView) -> None:
        """Keep the converged live field (reduced mean and covariance) every ``FIELD_KEEP_EVERY_S``."""
        live = view.live
        if live is None or not live.converged:
            return
        kept = self._fields
        if kept and live.t - kept[-1][0] < FIELD_KEEP_EVERY_S - 1e-6:
            return
        if kept and live.t < kept[-1][0]:  # the clock went back (a restart of the live state): start again
            kept.clear()
        kept.append((float(live.t), np.array(live.mean, dtype=float), np.array(live.cov, dtype=float)))

    def kept_span(self) -> tuple[float, float] | None:
        """(oldest, newest) epoch [s] of the live fields kept for probe readings (None: none yet)."""
        kept = list(self._fields)
        return None if not kept else (kept[0][0], kept[-1][0])

    def probes(self) -> list[ProbeMeasurement]:
        """The probe readings kept (restored and new, at most ``PROBES_KEPT``), newest first."""
        order = sorted(enumerate(self._probes), key=lambda im: (im[1].at, im[0]), reverse=True)
        return [m for _, m in order]  # taken later first among readings of one instant

    def _field_at(self, view: CoreView, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The kept live field (reduced mean, cov) nearest ``t`` [epoch s], the live one included;
        ``ProbeError`` naming ``at`` when ``t`` is outside what is kept."""
        cands = list(self._fields)
        live = view.live
        if live is not None and live.converged:
            cands.append((float(live.t), np.asarray(live.mean), np.asarray(live.cov)))
        if not cands:
            raise ProbeError(
                "at: no converged live field is kept yet; send the reading once the live state converged"
            )
        oldest, newest = cands[0][0], cands[-1][0]
        tol = FIELD_KEEP_EVERY_S
        if t < oldest - tol:
            raise ProbeError(
                f"at: {datetime.fromtimestamp(t, tz=UTC).isoformat()} is older than the live state's kept "
                f"history (from {datetime.fromtimestamp(oldest, tz=UTC).isoformat()})"
            )
        best = min(cands, key=lambda c: abs(c[0] - t))
        if abs(best[0] - t) > tol + DT_S:
            raise ProbeError(
                f"at: no live field kept within {tol + DT_S:.0f} s of "
                f"{datetime.fromtimestamp(t, tz=UTC).isoformat()} (newest "
                f"{datetime.fromtimestamp(newest, tz=UTC).isoformat()}; the live state restarted?)"
            )
        return best[1], best[2]

    def measure(
        self,
        view: CoreView,
        *,
        at: datetime,
        axial_um: float,
        sd_um: float,
        set_by: str = "api",
        source: str = "api",
    ) -> ProbeMeasurement:
        """Take a probe reading (the tool's axial position over the commissioned zero at ``at`` [µm], 1σ
        ``sd_um``): predict it from the live field kept nearest ``at`` and the mechanics in use, absorb it
        (a Kalman step, ``service.estimate.probe``) unless it lies beyond ``probe_gate_sigma`` σ of the
        prediction, and keep it (the caller stores it). Blocking (the basis, ~2 s the first time).
        ``ProbeError`` naming the field for a reading that cannot be used."""
        if not (math.isfinite(axial_um) and math.isfinite(sd_um) and sd_um > 0.0):
            raise ProbeError(f"axial_um, sd_um: need finite values and sd_um > 0, got {axial_um}, {sd_um}")
        if self._reference is None:
            raise ProbeError(
                "reference: no compensation zero is set; a reading is the growth over it (POST "
                "/api/v1/compensation/reference or chtc commission zero first)"
            )
        t = at.timestamp()
        mean, cov = self._field_at(view, t)
        ref = self.reference_for(view)
        if ref is None:
            raise ProbeError("at: no live field yet")
        t_ref, t_ref_sd, _ = ref
        ctx = self.prepare()
        basis = self.mechanics_basis()
        if ctx.phi is None:
            raise NotReadyError("probe readings need the reduced model's basis")
        with self._lock:
            if self._op_phi is None:
                self._op_phi = np.einsum("mjn,nr->mjr", basis.operators[0], ctx.phi)
            op_phi = self._op_phi
            feats = op_phi @ mean - basis.operators[0].sum(axis=2) * t_ref  # (2, 3) [µm]
            g_phi = ctx.g_phi[0] if ctx.g_phi is not None else ctx.g[0] @ ctx.phi
            g1 = float(ctx.g[0].sum())
            field_var = float(g_phi @ cov @ g_phi) + (g1 * t_ref_sd) ** 2
            base = self._mechanics if self._mechanics is not None else self._prior_calibration(at)
            up = absorb(
                base.mean,
                base.covariance,
                feats,
                float(axial_um),
                float(sd_um) ** 2 + field_var,
                gate_sigma=self.probe_gate_sigma,
            )
            m = ProbeMeasurement(
                at=at,
                axial_um=float(axial_um),
                sd_um=float(sd_um),
                features=tuple(tuple(float(v) for v in row) for row in feats),
                field_var_um2=field_var,
                predicted_um=up.predicted_um,
                sigma_um=up.sigma_um,
                innovation_um=up.innovation_um,
                accepted=up.accepted,
                set_by=set_by,
                source=source,
            )
            self._probes.append(m)
            if not up.accepted:
                return m
            n = int(base.report.get("probe_readings_absorbed", 0)) + 1
            cal = self._posterior(base, up.x, up.cov, n)
            assert self._base_ctx is not None
            self._ctx = self._calibrated(self._base_ctx, cal)  # the basis is built (above): cheap
            self._mechanics = cal
            self._terms.clear()
            self._pending = None
            self._estimate = None
        return m

    def section_operator(self) -> SectionOperator:
        """The section's outline and its displacement operators (once, ~0.2 s; blocking)."""
        ctx = self.prepare()
        with self._lock:
            if self._section_op is None:
                if ctx.phi is None:
                    raise NotReadyError("growth section unavailable: the model has no reduced basis")
                region = self.model.fe.element_region
                self._section_op = build_section(ctx.growth, region, ctx.phi)
            return self._section_op

    # --- stage 2
    def observe(self, view: CoreView) -> None:
        """Cheap (call after each event): with ``reference_on_first_start`` and no zero, take and store one
        from the first sample of a spindle at rest in equilibrium (``equilibrium_zero``); else freeze the
        provisional zero at the first converged live state."""
        self._keep_field(view)
        if self._reference is not None:
            return
        if self._first_start and self._first_start_zero(view):
            return
        live, ctx = view.live, self._ctx
        if self._provisional is not None or live is None or not live.converged:
            return
        if ctx is None or ctx.g_phi is None:  # built at start() off the loop; never here
            return
        t, sd = self._uniform_equivalent(ctx, view)
        with self._ref_lock:
            if self._provisional is None:
                self._provisional = (t, sd, datetime.fromtimestamp(live.t, tz=UTC))

    def _first_start_zero(self, view: CoreView) -> bool:
        s = view.newest
        if s is None:
            return False
        good = [q == "ok" for q in s.quality]
        offsets = view.calibration.applied() if view.calibration is not None else None
        zero = equilibrium_zero(s.temps_c, good, offsets, s.speed_rpm)
        if zero is None:
            return False
        with self._ref_lock:
            if self._reference is None:
                ref = CompensationReference(
                    temperature_c=zero[0],
                    sd_c=zero[1],
                    at=s.t,
                    source="first_start",
                    set_by=self._first_start_by,
                )
                self._reference = ref
                if self.on_reference is not None:
                    self.on_reference(ref)
        return True

    @staticmethod
    def zero_problem(ctx: GrowthContext, view: CoreView, sd_c: float) -> str | None:
        """Why the live field cannot give a zero now (None: it can): the live state has not converged, the
        spindle turns, or the zero's 1σ ``sd_c`` [°C] would add more than ``REFERENCE_MAX_SD_UM`` to the
        axial growth (at rest after a start, the part the sensors cannot see, the shaft's inside, is learnt
        within ~15 min)."""
        live = view.live
        if live is None:
            return "no live state yet"
        if not live.converged:
            return f"the live state has not converged ({live.reason})"
        if abs(live.inputs[1]) > 0.0:
            return f"the spindle turns ({live.inputs[1]:.0f} rpm); zero it at rest in equilibrium"
        sd_um = abs(float(ctx.g[0].sum())) * sd_c
        if not sd_um <= REFERENCE_MAX_SD_UM:
            return (
                f"the live field is not known well enough yet (the zero's 1σ would be {sd_um:.2f} µm > "
                f"{REFERENCE_MAX_SD_UM} µm); wait at rest"
            )
        return None

    # --- the reference
    @property
    def reference(self) -> CompensationReference | None:
        """The compensation reference in use (None: none set; the growth is then provisional)."""
        return self._reference

    def set_reference(self, ref: CompensationReference) -> None:
        """Use ``ref`` from now on (a restored or configured one: not reported to ``on_reference``)."""
        self._reference = ref

    def take_reference(
        self,
        view: CoreView,
        *,
        source: str,
        set_by: str,
        temperature_c: float | None = None,
        at: datetime | None = None,
    ) -> CompensationReference:
        """Set the reference now and report it to ``on_reference``: ``temperature_c`` [°C] as given (1σ 0),
        else the uniform equivalent of ``view``'s live field (``service.estimate.reference``), which needs a
        converged live state at rest that knows the field well enough (``zero_problem``; ``NotReadyError``
        naming it otherwise). ``at``: default the live state's instant."""
        live = view.live
        if temperature_c is None:
            ctx = self.prepare()
            t, sd = self._uniform_equivalent(ctx, view) if live is not None else (math.nan, math.nan)
            why = self.zero_problem(ctx, view, sd)
            if why is not None:
                raise NotReadyError(f"no reference taken: {why}; or give temperature_c")
        else:
            t, sd = float(temperature_c), 0.0
        when = at or (datetime.fromtimestamp(live.t, tz=UTC) if live is not None else datetime.now(UTC))
        ref = CompensationReference(temperature_c=t, sd_c=sd, at=when, source=source, set_by=set_by)
        with self._ref_lock:
            self._reference = ref
            if self.on_reference is not None:
                self.on_reference(ref)
        return ref

    @staticmethod
    def _uniform_equivalent(ctx: GrowthContext, view: CoreView) -> tuple[float, float]:
        live = view.live
        if live is None or ctx.g_phi is None:
            raise NotReadyError("no live state or no reduced basis: no uniform equivalent")
        g1 = float(ctx.g[0].sum())
        return uniform_equivalent(ctx.g_phi[0], g1, live.mean, live.cov)

    def reference_for(self, view: CoreView) -> tuple[float, float, datetime | None] | None:
        """(T_ref [°C], 1σ [°C], at) in use: the reference, else the provisional one, else the live field's
        own uniform equivalent (growth 0 until the live state converges); None: no live field."""
        self.observe(view)
        if self._reference is not None:
            r = self._reference
            return r.temperature_c, r.sd_c, r.at
        if self._provisional is not None:
            return self._provisional
        live = view.live
        if live is None:
            return None
        ctx = self._ctx
        if ctx is None or ctx.g_phi is None:
            return float(np.mean(live.field_c)), 0.0, None
        t, sd = self._uniform_equivalent(ctx, view)
        return t, sd, datetime.fromtimestamp(live.t, tz=UTC)

    @staticmethod
    def terms_key(view: CoreView) -> TermsKey | None:
        """What the condition terms depend on (None: nothing to serve yet)."""
        rec, live, cond = view.current, view.live, view.condition
        if live is None:
            return None
        held = (cond.id, cond.speed_rpm, cond.torque_nm, cond.ambient_c) if cond is not None else live.inputs
        return (None if rec is None else rec.id, tuple(live.h), tuple(live.load_scale), held)

    def wants_refresh(self, view: CoreView) -> bool:
        """True once per new key (the caller then runs ``refresh`` off the event loop)."""
        key = self.terms_key(view)
        with self._lock:
            if key is None or key in self._terms or key == self._pending:
                return False
            self._pending = key
            return True

    def refresh(self, view: CoreView) -> ConditionTerms | None:
        """The condition terms for ``view`` (computed ~0.25 s unless current; blocking)."""
        key = self.terms_key(view)
        if key is None or view.live is None:
            return None
        with self._lock:
            cached = self._terms.get(key)
            if cached is not None:
                self._terms.move_to_end(key)
                return cached
        speed_map = view.speed_map if view.map_serves else None
        cpu = time.thread_time()
        ctx = self.prepare()
        terms = self._compute_terms(ctx, view.live, view.condition, view.current, speed_map)
        with self._lock:
            self.computed += 1
            self.compute_cpu_s += time.thread_time() - cpu
            if ctx is not self._ctx:  # a commissioning changed the operators meanwhile: not cached
                if self._pending == key:
                    self._pending = None
                return terms
            self._terms[key] = terms
            while len(self._terms) > TERMS_KEPT:
                self._terms.popitem(last=False)
            if self._pending == key:
                self._pending = None
        return terms

    def _compute_terms(
        self,
        ctx: GrowthContext,
        live: FilterView,
        cond: ConditionSnapshot | None,
        rec: IdentificationRecord | None,
        speed_map: SpeedMap | None = None,
    ) -> ConditionTerms:
        """The terms at the held condition; Σ_H from ``rec``'s CIs (per-condition mode) or, in speed-map mode,
        from ``speed_map``'s band at the live state's speed and ambient (the H the live state uses); before
        the first identification (``rec`` None) the live state's guessed H with the widest band
        (``guessed_h_covariance``: at rest, with no heat input, the growth barely depends on H)."""
        from model.inputs import inputs_from_operation

        ambient, speed, torque = (
            (cond.ambient_c, cond.speed_rpm, cond.torque_nm) if cond is not None else live.inputs
        )
        inp = inputs_from_operation(
            self.model.spec, dt_s=DT_S, speed_rpm=speed, torque_nm=torque, ambient_c=ambient
        )
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

    def ready_for(self, view: CoreView) -> bool:
        """True when the condition terms for ``view`` are computed (a request then does dot products only)."""
        key = self.terms_key(view)
        with self._lock:
            return key is not None and key in self._terms

    # --- stage 3
    def estimate(self, view: CoreView) -> GrowthEstimate | None:
        """The growth of ``view``'s live field (None: no identification or no live state yet)."""
        live = view.live
        terms = self.refresh(view)
        if terms is None or live is None:
            return None
        ref = self.reference_for(view)
        if ref is None:
            return None
        t_ref, t_ref_sd, _ = ref
        key = (live.t, id(terms), t_ref, t_ref_sd, id(self._mechanics))
        cached = self._estimate
        if cached is not None and cached[0] == key:
            return cached[1]
        ctx = self.prepare()
        belief = field_belief(view)
        at = datetime.fromtimestamp(live.t, tz=UTC)
        est = estimate_growth(ctx, terms, belief, t_ref_c=t_ref, t_ref_sd_c=t_ref_sd, at=at)
        self._estimate = (key, est)
        return est

    def t_ref_c(self, view: CoreView) -> float | None:
        """The reference temperature of ``view``'s growth [°C] (None: no live field yet)."""
        ref = self.reference_for(view)
        return None if ref is None else ref[0]

    def section(self, view: CoreView) -> np.ndarray | None:
        """(u_r, u_z) (2, M) [µm] of the section's outline for ``view``'s live field (cached per live state
        and reference; None: no live field yet)."""
        live = view.live
        t_ref = self.t_ref_c(view)
        if live is None or t_ref is None:
            return None
        op = self.section_operator()
        key = (live.t, live.started_at, t_ref)
        cached = self._section
        if cached is not None and cached[0] == key:
            return cached[1]
        u = section_displacement_um(op, state=live.mean, t_ref_c=t_ref)
        self._section = (key, u)
        return u

    def section_snapshot(self, view: CoreView, now: datetime) -> SectionSnapshot | None:
        """What ``/compensation/section`` serves: the deformed outline of ``view``'s live field, with the
        status of ``/compensation`` (``snapshot``: None when it has nothing to serve)."""
        comp = self.snapshot(view, now)
        u = self.section(view)
        if comp is None or u is None:
            return None
        op = self.section_operator()
        return SectionSnapshot(
            at=comp.growth.at,
            t_ref_c=comp.growth.t_ref_c,
            nodes_rz=op.nodes_rz,
            edges=op.edges,
            u_um=u,
            status=comp.status,
            identification_id=comp.identification_id,
            newest_sample_at=comp.newest_sample_at,
        )

    def snapshot(self, view: CoreView, now: datetime) -> CompensationSnapshot | None:
        """What ``/compensation`` serves at ``now`` (UTC): the growth of ``view``'s live field and the
        policy's verdict on it (``service.serve.policy.compensation_verdict``: judged on the growth the
        controller applies, its CI against ``limits``, not on the H). ``identification_id``: the one whose H
        the growth used (None before the first identification: the live state's guessed H, the widest band,
        never usable: ``no_identification``). None before the live state's start."""
        est = self.estimate(view)
        rec = view.current
        if est is None:
            return None
        lo, hi = est.axial.ci95_um
        verdict = compensation_verdict(
            view,
            now,
            limits=self.limits,
            has_sample=view.newest is not None,
            ci95_half_um=0.5 * (hi - lo),
            identified_at=None if rec is None else rec.finished_at,
            has_reference=self._reference is not None,
            has_mechanics=self._commissioning is not None,
            # calibration off (no offset 1σ published): the operator handles the offsets, the rule is off
            has_offset_baseline=view.offset_sd_c is None or view.calibration is not None,
        )
        return CompensationSnapshot(
            growth=est,
            verdict=verdict,
            newest_sample_at=None if view.newest is None else view.newest.t,
            identification_id=None if rec is None else rec.id,
            plc=plc_compensation(est.axial.um, tool_dir=self.tool_dir),
            tool_dir=self.tool_dir,
            channels=tuple(s.channel for s in self.model.spec.sensors),
            reference=self._reference,
            mechanics=self._mechanics,
            sensor_faults=() if view.live is None else view.live.sensor_faults,
        )


class GrowthHistory:
    """The growth at each identification's end, offline (``run_offline``'s ``on_sample`` hook): after the
    sample whose identification succeeded (the live state then holds the filtered field), and the growth
    of that field is what ``/compensation`` would have served then (the same ``GrowthServer``, the same
    reference: ``t_ref_c``, by default the provisional zero, the first converged live field's). ``by_id``:
    identification id -> ``GrowthEstimate``; in combined mode an identification that does not serve (a map
    fit while the held condition's per-condition one does) gets the growth served then, the serving one's."""

    def __init__(self, model: LoadedModel, *, t_ref_c: float | None = None) -> None:
        self.model = model
        self.t_ref_c = t_ref_c
        self.by_id: dict[int, GrowthEstimate] = {}
        self._server: GrowthServer | None = None
        self._last_id = 0  # the newest identification id handled

    def __call__(self, core: ServiceCoreLike, k: int, last_ok: object) -> None:
        view = core.view()
        if self._server is None:
            self._server = GrowthServer(self.model, t_ref_c=self.t_ref_c)
            with contextlib.suppress(NotReadyError):  # built now: the provisional zero is the first converged
                self._server.prepare()  # live field's, as in the service (no mechanics: no growth at all)
        self._server.observe(view)
        rec = view.current
        if rec is None or view.current_from_restore:
            return
        # the identifications that succeeded since the last call (ids grow; newest first): each gets the
        # growth served now, the current one's (combined mode: a map fit at a held condition is not current)
        new = list(itertools.takewhile(lambda r: r.id > self._last_id, view.records))
        ok = [r.id for r in new if r.outcome == "ok" and r.id not in self.by_id]
        if not ok:
            return
        est = self._server.estimate(view)
        if est is not None:
            self._last_id = max(self._last_id, new[0].id)
            self.by_id.update(dict.fromkeys(ok, est))


class ServiceCoreLike(Protocol):
    """What ``GrowthHistory`` reads of ``service.engine.core.ServiceCore``."""

    def view(self) -> CoreView: ...
