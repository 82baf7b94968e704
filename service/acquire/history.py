"""Adapter from the acquisition ring buffer (``drivers.ringbuffer.RingBuffer``) to identification windows.

Speed and torque of samples whose CAN data were not fresh (``can_ok`` False: stale, faulted, never heard) are
treated as missing, like the ambient temperature the acquisition already sets to NaN when the DAQ flags it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from drivers.ringbuffer import RingBuffer
from service.identify.window import RawWindow

__all__ = ["RingHistory"]


class RingHistory:
    """``raw_window(t_from, t_to)`` over a ring buffer (epoch seconds, inclusive). ``suspect(t_from, t_to)``
    (optional): channels (n,) whose data in the window are not to be trusted (a stuck or drifting sensor the
    live state found, ``FilteredState.suspect_channels``): NaN in the whole window, so no fit uses them."""

    def __init__(
        self, ring: RingBuffer, suspect: Callable[[float, float], NDArray[np.bool_]] | None = None
    ) -> None:
        self.ring = ring
        self.suspect = suspect

    def raw_window(self, t_from: float, t_to: float) -> RawWindow:
        w = self.ring.window(t_from, t_to)
        can_ok = np.asarray(w.can_ok, dtype=bool)
        temps = np.asarray(w.temps_c, dtype=float)
        if self.suspect is not None:
            bad = self.suspect(t_from, t_to)
            if bad.any():
                temps = temps.copy()
                temps[:, bad] = np.nan
        return RawWindow(
            times_s=np.asarray(w.t, dtype=float),
            temps_c=temps,
            quality=np.asarray(w.quality, dtype=np.uint8),
            ambient_c=np.asarray(w.ambient_c, dtype=float),
            speed_rpm=np.where(can_ok, w.speed_rpm, np.nan),
            torque_nm=np.where(can_ok, w.torque_nm, np.nan),
        )
