"""Which compensation reference (growth 0: where the controller was zeroed) the served growth uses
(docs/commissioning.md, "Zero"): a commissioning fact, ``service.estimate.reference.CompensationReference``,
stored (``POST /compensation/reference``, ``chtc commission zero``) and restored at start, else the
configured ``compensation.reference_c`` (source "config"), else, if ``compensation.reference_on_first_start``
asks for it, taken from the first sample at rest in equilibrium and reported to be stored (source
"first_start"). With none, the growth is served against a provisional one (the uniform equivalent of the
first converged live field, with its 1σ; not stored) and is not usable (reason ``no_reference``). Pure
computation: no I/O; the clock is the live state's instants; one lock guards the reference, which API threads
and the loop share.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from datetime import UTC, datetime

import numpy as np
from numpy.typing import ArrayLike

from service.contracts.reference import CompensationReference
from service.estimate.growth import GrowthContext
from service.estimate.reference import equilibrium_zero, uniform_equivalent
from service.estimate.state import FilterView

__all__ = ["REFERENCE_MAX_SD_UM", "ReferenceBook", "live_uniform_equivalent", "zero_problem"]

REFERENCE_MAX_SD_UM = 0.1  # a zero taken from the live field adds at most this 1σ [µm] to the axial growth
Zero = tuple[float, float, datetime | None]  # (T_ref [°C], 1σ [°C], at)


def live_uniform_equivalent(ctx: GrowthContext, live: FilterView) -> tuple[float, float]:
    """The uniform equivalent temperature of ``live``'s field and its 1σ [°C] (``ctx`` has a reduced
    basis: ``g_phi``)."""
    assert ctx.g_phi is not None
    g1 = float(ctx.g[0].sum())
    return uniform_equivalent(ctx.g_phi[0], g1, live.mean, live.cov)


def zero_problem(ctx: GrowthContext, live: FilterView | None, sd_c: float) -> str | None:
    """Why the live field cannot give a zero now (None: it can): the live state has not converged, the
    spindle turns, or the zero's 1σ ``sd_c`` [°C] would add more than ``REFERENCE_MAX_SD_UM`` to the axial
    growth (at rest after a start, the part the sensors cannot see, the shaft's inside, is learnt within
    ~15 min)."""
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


class ReferenceBook:
    """See the module docstring. ``on_reference`` is told every reference taken here (the shell stores it)."""

    def __init__(
        self,
        reference: CompensationReference | None = None,
        *,
        t_ref_c: float | None = None,
        on_first_start: bool = False,
        first_start_by: str = "service",
        on_reference: Callable[[CompensationReference], None] | None = None,
    ) -> None:
        """``reference``: the stored one (restored); else ``t_ref_c`` [°C] (``compensation.reference_c``)
        makes a "config" one; ``on_first_start``: take one from the first sample at rest in equilibrium when
        there is none (``set_by`` ``first_start_by``)."""
        if reference is None and t_ref_c is not None:
            reference = CompensationReference(
                temperature_c=float(t_ref_c),
                sd_c=0.0,
                at=datetime.now(UTC),
                source="config",
                set_by="compensation.reference_c",
            )
        self._reference = reference
        self._first_start = bool(on_first_start)
        self._first_start_by = first_start_by
        self.on_reference = on_reference
        self._provisional: Zero | None = None  # (T, 1σ, at) until a reference exists
        self._lock = threading.RLock()  # API threads and the loop may both take the first-start one

    @property
    def reference(self) -> CompensationReference | None:
        """The compensation reference in use (None: none set; the growth is then provisional)."""
        return self._reference

    @property
    def wants_first_start(self) -> bool:
        """True while a first-start zero is asked for and none is set (``observe`` then needs ``newest``)."""
        return self._first_start and self._reference is None

    def set(self, ref: CompensationReference) -> None:
        """Use ``ref`` from now on (a restored or configured one: not reported to ``on_reference``)."""
        self._reference = ref

    def take(self, ref: CompensationReference) -> None:
        """Use ``ref`` from now on and report it to ``on_reference``."""
        with self._lock:
            self._reference = ref
            if self.on_reference is not None:
                self.on_reference(ref)

    def observe(
        self,
        live: FilterView | None,
        ctx: GrowthContext | None,
        newest: tuple[datetime, ArrayLike, ArrayLike, ArrayLike | None, float] | None,
    ) -> None:
        """Cheap (after each event): with ``on_first_start`` and no zero, take and report one from the first
        sample of a spindle at rest in equilibrium (``newest``: its instant, temperatures [°C], good
        channels, applied offsets [°C] or None, speed [rpm]; ``equilibrium_zero``); else freeze the
        provisional zero at the first converged live state (``ctx``: the growth context, if built)."""
        if self._reference is not None:
            return
        if self._first_start and newest is not None and self._first_start_zero(*newest):
            return
        if self._provisional is not None or live is None or not live.converged:
            return
        if ctx is None or ctx.g_phi is None:  # built at start() off the loop; never here
            return
        t, sd = live_uniform_equivalent(ctx, live)
        with self._lock:
            if self._provisional is None:
                self._provisional = (t, sd, datetime.fromtimestamp(live.t, tz=UTC))

    def _first_start_zero(
        self,
        at: datetime,
        temps_c: ArrayLike,
        good: ArrayLike,
        offsets: ArrayLike | None,
        speed_rpm: float,
    ) -> bool:
        zero = equilibrium_zero(temps_c, good, offsets, speed_rpm)
        if zero is None:
            return False
        with self._lock:
            if self._reference is None:
                ref = CompensationReference(
                    temperature_c=zero[0],
                    sd_c=zero[1],
                    at=at,
                    source="first_start",
                    set_by=self._first_start_by,
                )
                self._reference = ref
                if self.on_reference is not None:
                    self.on_reference(ref)
        return True

    def zero_for(self, live: FilterView | None, ctx: GrowthContext | None) -> Zero | None:
        """(T_ref [°C], 1σ [°C], at) in use: the reference, else the provisional one, else the live field's
        own uniform equivalent (growth 0 until the live state converges); None: no live field."""
        if self._reference is not None:
            r = self._reference
            return r.temperature_c, r.sd_c, r.at
        if self._provisional is not None:
            return self._provisional
        if live is None:
            return None
        if ctx is None or ctx.g_phi is None:
            return float(np.mean(live.field_c)), 0.0, None
        t, sd = live_uniform_equivalent(ctx, live)
        return t, sd, datetime.fromtimestamp(live.t, tz=UTC)
