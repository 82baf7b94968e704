"""What ``GET /compensation`` and ``/compensation/section`` serve: the thermal growth at the tool of a
published view, and the policy's verdict on it (docs/design/growth.md, "Serving"). The read path goes one way:
``api`` → ``service.serve`` (``ViewReader.compensation`` → :class:`GrowthServer`) → ``service.estimate`` (the
growth, its condition terms, the mechanics, the reference) → ``model``.

Three stages, by how often their inputs change:

- the growth context (operators of nose axial and radial growth, g·Φ): once per model, ``prepare()``; the
  shell calls it in a thread at ``start()``, otherwise the first request builds it (~0.7 s);
- the condition terms (steady field, modes, horizon functionals, sensor sensitivity): per (identification,
  condition, live H and load scales), ``refresh(view)``; the shell starts it in a thread when a published view
  has a new key (``wants_refresh``; ``service.shell.growthserve.TermsRefresher``), and a request whose key is
  not ready computes it in its own (API or outlet) thread (~0.25 s), never on the event loop, or waits for
  the computation of that key already running; the last 16 keys' terms are cached
  (``service.estimate.growthterms.TermsCache``);
- the estimate: per request, from the latest published ``CoreView`` (dot products).

The live field's uncertainty comes through ONE function, :func:`field_belief`. The mechanics and the probe
readings: ``service.estimate.mechbook.MechanicsBook``; the reference: ``service.estimate.referencebook``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime
from typing import TYPE_CHECKING

import numpy as np

from service.contracts.errors import NotReadyError
from service.contracts.growth import GrowthEstimate
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.probe import FixtureOffset, ProbeError, ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import CompensationSnapshot, SectionSnapshot
from service.estimate.growth import (
    ConditionTerms,
    FieldBelief,
    GrowthContext,
    estimate_growth,
    plc_compensation,
)
from service.estimate.growth_section import SectionOperator, build_section, section_displacement_um
from service.estimate.growthterms import TermsCache, held_terms, live_belief
from service.estimate.mechanics import ServedMechanicsBasis
from service.estimate.mechbook import MechanicsBook
from service.estimate.probe import ProbeTuning
from service.estimate.referencebook import ReferenceBook, live_uniform_equivalent, zero_problem
from service.serve.controlled import Controller, ControlLimits, ControlState
from service.serve.policy import CompensationLimits, compensation_limits, compensation_verdict
from service.serve.view import CoreView

if TYPE_CHECKING:
    from service.modelload import LoadedModel
    from service.settings import CompensationSettings

__all__ = ["GrowthServer", "TermsKey", "field_belief", "probe_tuning", "terms_key"]

TermsKey = tuple[object, ...]


def field_belief(view: CoreView) -> FieldBelief:
    """The live field's mean and uncertainty as the growth estimate takes it (``live_belief`` of ``view``'s
    live state: the filtered reduced mean and covariance, which hold the considered H error)."""
    return live_belief(view.live)


def terms_key(view: CoreView) -> TermsKey | None:
    """What the condition terms depend on (None: nothing to serve yet)."""
    rec, live, cond = view.current, view.live, view.condition
    if live is None:
        return None
    held = (cond.id, cond.speed_rpm, cond.torque_nm, cond.ambient_c) if cond is not None else live.inputs
    return (None if rec is None else rec.id, tuple(live.h), tuple(live.load_scale), held)


def probe_tuning(section: CompensationSettings) -> ProbeTuning:
    """The probe filter's tuning from ``[compensation]`` (the one mapping: ``chtc run``'s growth server and
    the default below call it)."""
    return ProbeTuning(
        gate_sigma=section.probe_gate_sigma,
        step_sigma=section.probe_step_sigma,
        offset_sd_um=section.probe_offset_sd_um,
        offset_q_um2_per_h=section.probe_offset_q_um2_per_h,
    )


def _default_probe_tuning() -> ProbeTuning:
    """The settings' ``[compensation]`` defaults (declared there; no environment)."""
    from service.settings import CompensationSettings

    return probe_tuning(CompensationSettings())


def _default_limits() -> CompensationLimits:
    """The policy's limits for a server built without them (the benches' and the offline history's, which
    judge the growth alone): the settings' ``[compensation]`` defaults (declared there; no environment)
    without the mechanics rule, which has no commissioning to read there."""
    from service.settings import CompensationSettings

    return replace(compensation_limits(CompensationSettings()), require_mechanics_calibration=False)


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
        probe: ProbeTuning | None = None,  # the settings' [compensation] probe_* (None: their defaults)
        control: ControlLimits
        | None = None,  # the CI gate and the command (None: neither, the plain verdict)
        control_state: ControlState | None = None,  # their checkpointed state (restored)
    ) -> None:
        """``reference``: the stored one (restored); else ``t_ref_c`` [°C] (``compensation.reference_c``)
        makes a "config" one; ``reference_on_first_start``: take one from the first sample at rest in
        equilibrium when there is none (``set_by`` ``first_start_by``); ``on_reference`` is told every
        reference taken here (the shell stores it); ``limits`` the settings' [compensation] (None:
        ``_default_limits``)."""
        self.limits = limits if limits is not None else _default_limits()
        self.model = model
        self.tool_dir = tool_dir
        self.references = ReferenceBook(
            reference,
            t_ref_c=t_ref_c,
            on_first_start=reference_on_first_start,
            first_start_by=first_start_by,
            on_reference=on_reference,
        )
        self.book = MechanicsBook(
            model,
            context=context,
            mechanics=mechanics,
            basis=mechanics_basis,
            probes=probes,
            tuning=probe if probe is not None else _default_probe_tuning(),
        )
        self.terms = TermsCache()
        # the CI gate and the command value, stepped on every snapshot (each published sample and each read)
        self.controller = (
            None if control is None else Controller(control, tool_dir=tool_dir, state=control_state)
        )
        self._estimate: tuple[tuple[object, ...], GrowthEstimate] | None = None
        self._section_op: SectionOperator | None = None
        self._section: tuple[tuple[object, ...], np.ndarray] | None = None

    # --- stage 1: the context and the mechanics
    def prepare(self) -> GrowthContext:
        """The growth context (built once, ~0.7 s; blocking: call it off the event loop). ``NotReadyError``
        naming the cause when the spindle description has no usable mechanics (tried once)."""
        ctx = self.book.context()
        if ctx is None:
            raise NotReadyError(self.book.error or "growth model unavailable")
        return ctx

    @property
    def on_reference(self) -> Callable[[CompensationReference], None] | None:
        return self.references.on_reference

    @on_reference.setter
    def on_reference(self, fn: Callable[[CompensationReference], None] | None) -> None:
        self.references.on_reference = fn

    @property
    def mechanics(self) -> MechanicsCalibration | None:
        """The mechanics in use (``MechanicsBook.mechanics``)."""
        return self.book.mechanics

    @property
    def commissioning(self) -> MechanicsCalibration | None:
        """The commissioning (stored or set), before any probe reading (None: not commissioned)."""
        return self.book.commissioning

    @property
    def fixture_offset(self) -> FixtureOffset | None:
        """The fixture offset the probe readings measured (``MechanicsBook.fixture_offset``)."""
        return self.book.fixture_offset

    @property
    def computed(self) -> int:
        """Condition terms computed (cache misses)."""
        return self.terms.computed

    @property
    def compute_cpu_s(self) -> float:
        """Their CPU [s]."""
        return self.terms.compute_cpu_s

    def mechanics_basis(self) -> ServedMechanicsBasis:
        """The served outputs' mount/α operators (built once, ~2 s; blocking)."""
        return self.book.basis()

    def set_mechanics(self, cal: MechanicsCalibration) -> None:
        """Serve with ``cal`` from now on (blocking: may build the basis; call it off the event loop): the
        condition terms, which depend on the operators, are recomputed on the next request."""
        self.prepare()
        self.book.basis()
        self.book.set(cal)
        self._changed()

    def _changed(self) -> None:
        self.terms.clear()
        self._estimate = None

    def probes(self) -> list[ProbeMeasurement]:
        """The probe readings kept (restored and new), newest first."""
        return self.book.probes()

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
        unless it lies beyond ``probe.gate_sigma`` σ of the prediction (or as a step of the fixture offset,
        ``service.estimate.probe``), and keep it (the caller stores it).
        Blocking (the basis, ~2 s the first time). ``ProbeError`` naming the field for a reading that cannot
        be used."""
        if not (math.isfinite(axial_um) and math.isfinite(sd_um) and sd_um > 0.0):
            raise ProbeError(f"axial_um, sd_um: need finite values and sd_um > 0, got {axial_um}, {sd_um}")
        if self.references.reference is None:
            raise ProbeError(
                "reference: no compensation zero is set; a reading is the growth over it (POST "
                "/api/v1/compensation/reference or chtc commission zero first)"
            )
        field = self.book.field_at(view.live, at.timestamp())
        ref = self.reference_for(view)
        if ref is None:
            raise ProbeError("at: no live field yet")
        ctx = self.prepare()
        self.book.basis()
        if ctx.phi is None:
            raise NotReadyError("probe readings need the reduced model's basis")
        before = self.book.mechanics
        m = self.book.absorb_reading(
            ctx,
            field,
            t_ref=ref[0],
            t_ref_sd=ref[1],
            at=at,
            axial_um=axial_um,
            sd_um=sd_um,
            set_by=set_by,
            source=source,
        )
        if self.book.mechanics is not before:
            self._changed()
        return m

    # --- the reference
    @property
    def reference(self) -> CompensationReference | None:
        """The compensation reference in use (None: none set; the growth is then provisional)."""
        return self.references.reference

    def set_reference(self, ref: CompensationReference) -> None:
        """Use ``ref`` from now on (a restored or configured one: not reported to ``on_reference``)."""
        self.references.set(ref)

    def observe(self, view: CoreView) -> None:
        """Cheap (call after each event): keep the live field for probe readings; with
        ``reference_on_first_start`` and no zero, take and store one from the first sample of a spindle at
        rest in equilibrium; else freeze the provisional zero at the first converged live state."""
        self.book.keep_field(view.live)
        s = view.newest
        newest = None
        if s is not None and self.references.wants_first_start:
            good = [q == "ok" for q in s.quality]
            offsets = view.calibration.applied() if view.calibration is not None else None
            newest = (s.t, s.temps_c, good, offsets, s.speed_rpm)
        self.references.observe(view.live, self.book.current, newest)

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
            if live is not None and ctx.g_phi is None:
                raise NotReadyError("no live state or no reduced basis: no uniform equivalent")
            t, sd = live_uniform_equivalent(ctx, live) if live is not None else (math.nan, math.nan)
            why = zero_problem(ctx, live, sd)
            if why is not None:
                raise NotReadyError(f"no reference taken: {why}; or give temperature_c")
        else:
            t, sd = float(temperature_c), 0.0
        when = at or (datetime.fromtimestamp(live.t, tz=UTC) if live is not None else datetime.now(UTC))
        ref = CompensationReference(temperature_c=t, sd_c=sd, at=when, source=source, set_by=set_by)
        self.references.take(ref)
        return ref

    def reference_for(self, view: CoreView) -> tuple[float, float, datetime | None] | None:
        """(T_ref [°C], 1σ [°C], at) in use: the reference, else the provisional one, else the live field's
        own uniform equivalent (growth 0 until the live state converges); None: no live field."""
        self.observe(view)
        return self.references.zero_for(view.live, self.book.current)

    def t_ref_c(self, view: CoreView) -> float | None:
        """The reference temperature of ``view``'s growth [°C] (None: no live field yet)."""
        ref = self.reference_for(view)
        return None if ref is None else ref[0]

    # --- stage 2: the condition terms
    def wants_refresh(self, view: CoreView) -> bool:
        """True once per new key (the caller then runs ``refresh`` off the event loop)."""
        key = terms_key(view)
        return key is not None and self.terms.claim(key)

    def refresh(self, view: CoreView) -> ConditionTerms | None:
        """The condition terms for ``view`` (computed ~0.25 s unless current; blocking)."""
        key = terms_key(view)
        live = view.live
        if key is None or live is None:
            return None
        speed_map = view.speed_map if view.map_serves else None
        cond = view.condition
        held = (cond.ambient_c, cond.speed_rpm, cond.torque_nm) if cond is not None else None

        def compute() -> tuple[ConditionTerms, object]:
            ctx = self.prepare()
            # compact: the live belief is reduced, and 16 keys of nodal functionals cost ~20 MiB a spindle
            return held_terms(ctx, self.model.spec, live, held, view.current, speed_map).compact(), ctx

        return self.terms.get(key, compute, lambda: self.book.current)

    def ready_for(self, view: CoreView) -> bool:
        """True when the condition terms for ``view`` are computed (a request then does dot products only)."""
        key = terms_key(view)
        return key is not None and key in self.terms

    # --- stage 3: the estimate, the section, the snapshots
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
        key = (live.t, id(terms), t_ref, t_ref_sd, id(self.book.mechanics))
        cached = self._estimate
        if cached is not None and cached[0] == key:
            return cached[1]
        ctx = self.prepare()
        at = datetime.fromtimestamp(live.t, tz=UTC)
        est = estimate_growth(ctx, terms, field_belief(view), t_ref_c=t_ref, t_ref_sd_c=t_ref_sd, at=at)
        self._estimate = (key, est)
        return est

    def section_operator(self) -> SectionOperator:
        """The section's outline and its displacement operators (once, ~0.2 s; blocking)."""
        ctx = self.prepare()
        with self.book.lock:
            if self._section_op is None:
                if ctx.phi is None:
                    raise NotReadyError("growth section unavailable: the model has no reduced basis")
                region = self.model.fe.element_region
                self._section_op = build_section(ctx.growth, region, ctx.phi)
            return self._section_op

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
            has_reference=self.reference is not None,
            has_mechanics=self.commissioning is not None,
            # calibration off (no offset 1σ published): the operator handles the offsets, the rule is off
            # a commissioning's baseline counts once its check has ended (it may not fit these sensors)
            has_offset_baseline=view.offset_sd_c is None
            or (view.calibration is not None and not view.offsets_unchecked),
        )
        plain, command = verdict, None
        if self.controller is not None:
            verdict, command = self.controller.step(
                now.timestamp(), plain, growth_um=est.axial.um, half_um=0.5 * (hi - lo)
            )
        return CompensationSnapshot(
            growth=est,
            verdict=verdict,
            policy_verdict=plain,
            command=command,
            newest_sample_at=None if view.newest is None else view.newest.t,
            identification_id=None if rec is None else rec.id,
            plc=plc_compensation(est.axial.um, tool_dir=self.tool_dir),
            tool_dir=self.tool_dir,
            channels=tuple(s.channel for s in self.model.spec.sensors),
            reference=self.reference,
            mechanics=self.mechanics,
            fixture_offset=self.fixture_offset,
            sensor_faults=() if view.live is None else view.live.sensor_faults,
        )
