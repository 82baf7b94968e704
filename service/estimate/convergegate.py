"""When the live state may serve and start identification windows (``service.estimate.state.FilteredState``):
converged since the (re)start, and, after an open-loop run longer than ``max_gap_s`` (no usable temperature:
a DAQ outage with CAN alive), re-acquired (the convergence test passed again on data). Pure."""

from __future__ import annotations

from dataclasses import dataclass

from model.estimator import Convergence

__all__ = ["ConvergenceGate"]


@dataclass
class ConvergenceGate:
    """``converged_at`` [s] the first converged sample since the (re)start; ``reacquiring`` while the state
    re-acquires after a long open-loop run, ``reacquired_at`` [s] when it passed the test again;
    ``blind_from`` [s] the start of the current run of steps without an update; ``last`` the last test."""

    max_gap_s: float
    converged_at: float | None = None
    reacquiring: bool = False
    reacquired_at: float | None = None
    blind_from: float | None = None
    last: Convergence | None = None

    def restart(self, converged_at: float | None = None) -> None:
        """A (re)start: not converged; or ``converged_at`` (a converged checkpoint), then re-acquiring."""
        self.converged_at = converged_at
        self.blind_from, self.reacquiring, self.reacquired_at = None, converged_at is not None, None
        self.last = None

    @property
    def initial(self) -> bool:
        """Windows should not start on the state now (not converged, or re-acquiring)."""
        return self.converged_at is None or self.reacquiring

    def testing(self, dof: int) -> bool:
        """Whether this step runs the convergence test (not converged yet, or re-acquiring on data)."""
        return self.converged_at is None or (self.reacquiring and bool(dof))

    def passed(self, t: float) -> None:
        """The test passed at ``t`` [s]: converged, or re-acquired."""
        if self.converged_at is None:
            self.converged_at = t
        else:
            self.reacquiring, self.reacquired_at = False, t

    def track_blind(self, t: float, n: int, dt_s: float, dof: int) -> bool:
        """Follow runs of steps without a measurement update (``n`` steps of ``dt_s`` ending at ``t`` [s],
        ``dof`` channels used); past ``max_gap_s`` the state re-acquires. True: the convergence gate's NIS
        window starts again (the first update on data after such a run)."""
        if dof:
            regate = self.reacquiring and self.blind_from is not None
            self.blind_from = None
            return regate
        if self.blind_from is None:
            self.blind_from = t - n * dt_s
        if self.converged_at is not None and t - self.blind_from > self.max_gap_s:
            self.reacquiring = True
        return False

    def after_open_loop(self, dof: int) -> bool:
        """The first update (``dof`` > 0) after an open-loop run longer than ``max_gap_s``."""
        return self.reacquiring and self.blind_from is not None and dof > 0

    def ready_at(self) -> float | None:
        """Earliest window start [s] allowed: the first converged sample since the (re)start, or after the
        last open-loop run longer than ``max_gap_s`` the first sample the state passed the convergence test
        on data again (None: not yet)."""
        if self.reacquiring:
            return None
        if self.converged_at is None or self.reacquired_at is None:
            return self.converged_at
        return max(self.converged_at, self.reacquired_at)

    def reason(self) -> str:
        """Why the state is (not) converged: "converged", the last test's reason, or "starting"."""
        if self.converged_at is not None:
            return "converged"
        return self.last.reason if self.last is not None else "starting"
