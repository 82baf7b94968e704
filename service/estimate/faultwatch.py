"""The sensor-fault monitor as the live state uses it (pure): which channels an update may use, what a newly
found fault had bent so far (charged to the unknown offsets' share of the state's error), and the faults found
or recovered since the last step. Without a monitor (``FilterSettings.faults`` None) every usable channel is
used and nothing is ever suspect."""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from model.estimator import NoiseModel
from service.estimate.offsetbias import OffsetBias
from service.estimate.sensorfaults import FaultChange, FaultMonitor, FaultMonitorSettings, SensorFault

__all__ = ["FaultWatch"]


class Predicted(Protocol):
    """What ``observe`` reads of an update (``model.estimator.StepResult``)."""

    @property
    def predicted_c(self) -> NDArray[np.float64]: ...

    @property
    def predicted_std_c(self) -> NDArray[np.float64]: ...


class FaultWatch:
    """One live state's fault monitor (None: off) and the offset bias it charges."""

    def __init__(self, monitor: FaultMonitor | None, bias: OffsetBias) -> None:
        self.monitor = monitor
        self._bias = bias
        self._changes: list[FaultChange] = []

    @classmethod
    def of(
        cls, settings: FaultMonitorSettings | None, n: int, noise: NoiseModel, bias: OffsetBias
    ) -> FaultWatch:
        """The watch for ``n`` channels with ``settings`` (None: no monitor)."""
        monitor = None if settings is None else FaultMonitor(n, noise_c=noise.sigma_meas_c, settings=settings)
        return cls(monitor, bias)

    def usable(self, ok: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """The channels of ``ok`` an update may use: none that is stuck or drifting now."""
        return ok if self.monitor is None else ok & ~self.monitor.excluded()

    def observe(
        self,
        t: float,
        y: NDArray[np.float64],
        ok: NDArray[np.bool_],
        res: Predicted,
        offsets_c: NDArray[np.float64],
    ) -> None:
        """Feed one update's readings ``y`` and predictions to the monitor; a fault found now charges what
        its readings bent so far to the state's uncertainty."""
        if self.monitor is None:
            return
        changes = self.monitor.observe(t, y, ok, res.predicted_c, res.predicted_std_c, offsets_c)
        for ch in changes:
            if not ch.recovered:
                self._bias.charge(ch.fault.index, ch.bias_c)
        self._changes.extend(changes)

    def restart(self) -> None:
        """The live state restarted from its prior: every channel starts unsuspected again."""
        if self.monitor is not None:
            self.monitor.restart()

    def take_changes(self) -> tuple[FaultChange, ...]:
        """The faults found or recovered since the last call."""
        changes, self._changes = tuple(self._changes), []
        return changes

    def suspect(self, t_from: float, t_to: float) -> NDArray[np.bool_]:
        """Channels whose data in [t_from, t_to] [s] a window must leave out (``FaultMonitor.suspect``)."""
        if self.monitor is None:
            return np.zeros(self._bias.n, dtype=bool)
        return self.monitor.suspect(t_from, t_to)

    def active(self) -> tuple[SensorFault, ...]:
        """The channels left out of the updates now."""
        return () if self.monitor is None else self.monitor.active()
