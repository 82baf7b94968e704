"""The mechanics the served growth uses, and the probe readings that update them (docs/commissioning.md,
"Commission the growth", "Probe measurements"): the growth context (operators of nose axial and radial
growth, g·Φ; built once per model, ~0.7 s), calibrated with the commissioning updated by the readings
absorbed since (``service.estimate.mechanics``, ``service.estimate.probe``), and the fixture offset those
readings measured (added to the served axial growth with its variance once one is absorbed). Pure
computation: no I/O, no clock; one lock guards the state, which the API threads and the shell's worker
threads share.

Without a commissioning the operators are the spindle description's (``[mechanics]`` as written) and the
policy's ``mechanics_uncalibrated`` rule applies; with one (restored or ``set``) the operators are the
calibrated ones and every CI carries the mechanical posterior (``service.estimate.growth.with_mechanics``).
"""

from __future__ import annotations

import collections
import dataclasses
import threading
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Protocol

import numpy as np

from service.contracts.mechanics import MechanicsCalibration
from service.contracts.probe import PROBES_KEPT, FixtureOffset, ProbeError, ProbeMeasurement
from service.estimate.growth import GrowthContext, build_context, with_mechanics
from service.estimate.growthterms import DT_S
from service.estimate.mechanics import ServedMechanicsBasis, served_mechanics_basis
from service.estimate.probe import (
    ProbeState,
    ProbeTuning,
    prior_covariance,
    prior_mean,
    replay_state,
    start_state,
    take_reading,
)
from service.estimate.state import FilterView

if TYPE_CHECKING:
    from model.fem import FEModel
    from model.geometry import SpindleSpec
    from model.rom import ReducedModel


class SpindleModel(Protocol):
    """What the book reads of the service's model (``service.modelload.LoadedModel``)."""

    @property
    def spec(self) -> SpindleSpec: ...

    @property
    def fe(self) -> FEModel: ...

    @property
    def rom(self) -> ReducedModel: ...


__all__ = ["FIELD_KEEP_EVERY_S", "FIELD_KEEP_S", "MechanicsBook", "fixture_offset", "prior_calibration"]

FIELD_KEEP_S = 3 * 3600.0  # the live fields kept for probe readings: the live state's own history (keep_s)
FIELD_KEEP_EVERY_S = 30.0  # one kept every this [s]; a reading takes the nearest
Kept = tuple[float, np.ndarray, np.ndarray]  # (epoch [s], reduced mean, reduced covariance)


def prior_calibration(at: datetime) -> MechanicsCalibration:
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


def posterior(base: MechanicsCalibration, state: ProbeState) -> MechanicsCalibration:
    """``base`` with θ of the probe filter's ``state`` (clipped to the calibration's range) and Σ_θ, after its
    readings (the offset b is served beside it: ``fixture_offset``)."""
    x, cov = state.mechanics
    xs = (
        float(np.clip(x[0], 0.0, 1.0)),
        float(np.clip(x[1], 0.51, 1.49)),
        float(np.clip(x[2], 0.51, 1.49)),
    )
    report = {**base.report, "probe_readings_absorbed": state.absorbed}
    return dataclasses.replace(
        base, x=xs, cov=tuple(tuple(float(v) for v in row) for row in cov), report=report
    )


def fixture_offset(state: ProbeState | None) -> FixtureOffset | None:
    """The offset the probe filter's ``state`` estimates (None: no reading absorbed since the commissioning:
    the growth is then relative to the commissioned zero, as it always was)."""
    if state is None or state.absorbed == 0:
        return None
    b, var, cov_tb = state.offset
    return FixtureOffset(
        um=b,
        sd_um=float(np.sqrt(max(var, 0.0))),
        cov_mech_um=(float(cov_tb[0]), float(cov_tb[1]), float(cov_tb[2])),
        readings=state.absorbed,
        at=datetime.fromtimestamp(state.t, tz=UTC),
        steps=state.steps,
    )


def replayed(
    cal: MechanicsCalibration | None, probes: tuple[ProbeMeasurement, ...], tuning: ProbeTuning
) -> tuple[MechanicsCalibration | None, ProbeState | None]:
    """``cal`` (None: the prior from the first reading on) after the readings measured after it (oldest
    first; their stored decisions, ``service.estimate.probe.replay_state``) and the probe filter's state
    (None: no commissioning and no reading); ``cal`` itself when none was absorbed."""
    use = sorted((m for m in probes if cal is None or m.at > cal.at), key=lambda m: m.at)
    if cal is None and not use:
        return None, None
    base = cal if cal is not None else prior_calibration(use[0].at)
    state = replay_state(start_state(base.mean, base.covariance, base.at.timestamp(), tuning), use, tuning)
    return (posterior(base, state) if state.absorbed else cal), state


class MechanicsBook:
    """See the module docstring. ``context()`` builds the growth context once (None, with ``error`` naming
    the cause, when the spindle description has no usable mechanics; tried once)."""

    def __init__(
        self,
        model: SpindleModel,  # read on first use only
        *,
        context: GrowthContext | None = None,  # built already (the bench shares one across runs)
        mechanics: MechanicsCalibration | None = None,  # the stored commissioning (restored)
        basis: ServedMechanicsBasis | None = None,  # built already (tests, benches)
        probes: tuple[ProbeMeasurement, ...] = (),  # the stored probe readings (restored), oldest first
        tuning: ProbeTuning,  # the settings' [compensation] probe_* (``service.serve.compensation``)
    ) -> None:
        self.model = model
        self.lock = threading.Lock()
        self.error: str | None = None
        self.tuning = tuning
        self._commissioning = mechanics
        self._probes: collections.deque[ProbeMeasurement] = collections.deque(probes, maxlen=PROBES_KEPT)
        self._fields: collections.deque[Kept] = collections.deque(
            maxlen=int(FIELD_KEEP_S / FIELD_KEEP_EVERY_S) + 2
        )
        self._op_phi: np.ndarray | None = None  # the axial mount/α operators on the reduced basis (2, 3, r)
        self._mechanics, self._state = replayed(mechanics, probes, tuning)
        self._basis = basis
        self._base_ctx: GrowthContext | None = context  # the described mechanics' context
        self._ctx: GrowthContext | None = context if self._mechanics is None else None  # else: calibrated

    # --- the context
    def context(self) -> GrowthContext | None:
        """The growth context in use (built once, ~0.7 s; blocking: call it off the event loop)."""
        with self.lock:
            if self._ctx is None and self.error is None:
                m = self.model
                try:
                    if self._base_ctx is None:
                        self._base_ctx = build_context(m.spec, m.fe, basis=m.rom.basis)
                    self._ctx = self._calibrated(self._base_ctx, self._mechanics, self._state)
                except Exception as err:  # any failure of the optional growth model: served as 503
                    self.error = f"growth model unavailable: {type(err).__name__}: {err}"
            return self._ctx

    @property
    def current(self) -> GrowthContext | None:
        """The context built so far (None: not yet), never building it."""
        return self._ctx

    def _calibrated(
        self, base: GrowthContext, cal: MechanicsCalibration | None, state: ProbeState | None
    ) -> GrowthContext:
        """``base`` with ``cal``'s operators and posterior and the fixture offset of ``state`` (the basis
        built once, ~2 s); ``base`` if ``cal`` is None."""
        if cal is None:
            return base
        if self._basis is None:
            self._basis = served_mechanics_basis(self.model.spec, self.model.fe)
        b = self._basis
        off = fixture_offset(state)
        return with_mechanics(
            base,
            b.operators_at(cal.x),
            b.jacobian_at(cal.x),
            cal.covariance,
            offset=None if off is None else (off.um, off.sd_um**2, off.cov_mech_um),
        )

    def basis(self) -> ServedMechanicsBasis:
        """The served outputs' mount/α operators (built once, ~2 s; blocking)."""
        with self.lock:
            if self._basis is None:
                self._basis = served_mechanics_basis(self.model.spec, self.model.fe)
            return self._basis

    # --- the mechanics
    @property
    def mechanics(self) -> MechanicsCalibration | None:
        """The mechanics in use: the commissioning updated by the probe readings absorbed since (None: the
        described mechanics, uncalibrated, and no reading absorbed)."""
        return self._mechanics

    @property
    def fixture_offset(self) -> FixtureOffset | None:
        """The fixture offset the probe readings measured (None: none absorbed since the commissioning)."""
        return fixture_offset(self._state)

    @property
    def commissioning(self) -> MechanicsCalibration | None:
        """The commissioning (stored or set), before any probe reading (None: not commissioned)."""
        return self._commissioning

    def set(self, cal: MechanicsCalibration) -> None:
        """Use ``cal`` from now on; the context must be built (``context()``) and the basis (``basis()``)."""
        with self.lock:
            assert self._base_ctx is not None
            self._state = start_state(cal.mean, cal.covariance, cal.at.timestamp(), self.tuning)
            self._ctx = self._calibrated(self._base_ctx, cal, self._state)
            self._mechanics = cal
            self._commissioning = cal

    # --- probe readings
    def keep_field(self, live: FilterView | None) -> None:
        """Keep the converged live field (reduced mean and covariance) every ``FIELD_KEEP_EVERY_S``."""
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

    def field_at(self, live: FilterView | None, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The kept live field (reduced mean, cov) nearest ``t`` [epoch s], the live one included;
        ``ProbeError`` naming ``at`` when ``t`` is outside what is kept."""
        cands = list(self._fields)
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

    def absorb_reading(
        self,
        ctx: GrowthContext,
        field: tuple[np.ndarray, np.ndarray],
        *,
        t_ref: float,
        t_ref_sd: float,
        at: datetime,
        axial_um: float,
        sd_um: float,
        set_by: str,
        source: str,
    ) -> ProbeMeasurement:
        """Predict the reading from the kept ``field`` (reduced mean, cov), the mechanics and the fixture
        offset in use, absorb it (a Kalman step, ``service.estimate.probe``) unless it lies beyond
        ``tuning.gate_sigma`` σ of the prediction (or as a step of the offset, right after a consistent gated
        one), and keep it. ``ctx`` (with its reduced basis) and the basis are built already."""
        mean, cov = field
        basis = self.basis()
        assert ctx.phi is not None
        with self.lock:
            if self._op_phi is None:
                self._op_phi = np.einsum("mjn,nr->mjr", basis.operators[0], ctx.phi)
            feats = self._op_phi @ mean - basis.operators[0].sum(axis=2) * t_ref  # (2, 3) [µm]
            g_phi = ctx.g_phi[0] if ctx.g_phi is not None else ctx.g[0] @ ctx.phi
            g1 = float(ctx.g[0].sum())
            field_var = float(g_phi @ cov @ g_phi) + (g1 * t_ref_sd) ** 2
            base = self._mechanics if self._mechanics is not None else prior_calibration(at)
            state = self._state
            if state is None:
                state = start_state(base.mean, base.covariance, at.timestamp(), self.tuning)
            var = float(sd_um) ** 2 + field_var
            state, up = take_reading(state, feats, float(axial_um), var, at.timestamp(), self.tuning)
            self._state = state
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
                offset_step=up.offset_step,
                set_by=set_by,
                source=source,
            )
            self._probes.append(m)
            if not up.accepted:
                return m
            cal = posterior(base, state)
            assert self._base_ctx is not None
            self._ctx = self._calibrated(self._base_ctx, cal, state)  # the basis is built (above): cheap
            self._mechanics = cal
        return m
