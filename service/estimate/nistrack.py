"""The live state's normalised innovations (NIS): the health window (its verdict, ``high_since``), the shorter
window of the convergence gate, the last sample's and the kept history (``service.estimate.state``). Pure."""

from __future__ import annotations

from collections import deque
from typing import Any

from model.estimator import NisWindow

__all__ = ["NisTrack"]


class NisTrack:
    """``window`` the health test's ``window_n`` samples, ``gate`` the convergence gate's ``gate_n``;
    ``last`` (NIS, dof) of the last sample; ``high_since`` [s] the verdict "high" since (None: not high);
    ``history`` (t [s], NIS, dof) of the last ``keep`` samples with an update."""

    def __init__(self, window_n: int, gate_n: int, *, keep: int) -> None:
        self.window_n, self.gate_n = int(window_n), int(gate_n)
        self.window = NisWindow(self.window_n)
        self.gate = NisWindow(self.gate_n)
        self.last: tuple[float, int] = (0.0, 0)
        self.high_since: float | None = None
        self.history: deque[tuple[float, float, int]] = deque(maxlen=keep)

    def restart(self) -> None:
        """The state restarted: both windows empty, not high."""
        self.window = NisWindow(self.window_n)
        self.gate = NisWindow(self.gate_n)
        self.high_since = None

    def regate(self) -> None:
        """The convergence gate starts again (the first update on data after an open-loop run)."""
        self.gate = NisWindow(self.gate_n)

    def push(self, t: float, nis: float, dof: int) -> str:
        """One sample's NIS over ``dof`` channels (0, 0 without an update) at ``t`` [s]; returns the window's
        verdict."""
        self.window.push(nis, dof)
        self.gate.push(nis, dof)
        if dof:
            self.history.append((t, nis, dof))
        self.last = (nis, dof)
        verdict = self.window.verdict()
        if verdict != "high":
            self.high_since = None
        elif self.high_since is None:
            self.high_since = t
        return verdict

    def view_fields(self) -> dict[str, Any]:
        """The NIS fields of ``service.estimate.state.FilterView``."""
        total, dof = self.window.totals()
        return {
            "nis": self.last[0],
            "nis_dof": self.last[1],
            "verdict": self.window.verdict(),
            "nis_sum": total,
            "nis_sum_dof": dof,
            "nis_band": self.window.band(),
            "high_since": self.high_since,
        }
