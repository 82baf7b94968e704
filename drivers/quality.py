"""Per-channel quality flags shared by the drivers, the ring buffer and the service.

Stored as ``uint8`` in arrays (``Quality(x)`` converts back). Only ``OK`` channels enter the fit;
everything else is masked out and shown to the user with its flag. When several conditions apply, the
first in ``PRECEDENCE`` wins: a channel the DAQ flags open-circuit is ``OPEN_CIRCUIT`` even if it also
repeats.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
import numpy.typing as npt


class Quality(IntEnum):
    """Why a value may or may not be trusted."""

    OK = 0
    STALE = 1  # the device stopped delivering new data (counter not advancing, CAN silence, timeout)
    OPEN_CIRCUIT = 2  # DAQ status 1: sensor wire broken
    OUT_OF_RANGE = 3  # DAQ status 2, or a value outside the configured plausible range
    NAN = 4  # not a number (float32 NaN, or the int16 sentinel 0x8000)
    STUCK = 5  # value unchanged for longer than the stuck limit
    NO_DATA = 6  # nothing received yet
    FAULT = 7  # the device itself reports a fault (CAN status byte 2)

    @property
    def label(self) -> str:
        """Lower-case name used in JSON and the API: "ok", "stale", "open_circuit", ..."""
        return self.name.lower()


# Highest first: when several conditions hold at once, the first in this tuple is reported.
PRECEDENCE: tuple[Quality, ...] = (
    Quality.NO_DATA,
    Quality.STALE,
    Quality.FAULT,
    Quality.OPEN_CIRCUIT,
    Quality.OUT_OF_RANGE,
    Quality.NAN,
    Quality.STUCK,
    Quality.OK,
)

_DAQ_STATUS: dict[int, Quality] = {0: Quality.OK, 1: Quality.OPEN_CIRCUIT, 2: Quality.OUT_OF_RANGE}


def from_daq_status(code: int) -> Quality:
    """Map a DAQ per-channel status register (0 ok, 1 open circuit, 2 out of range) to a flag.

    Unknown codes are reported as ``OUT_OF_RANGE`` (the device says "not ok" without saying why).
    """
    return _DAQ_STATUS.get(int(code), Quality.OUT_OF_RANGE)


def worst(*flags: Quality) -> Quality:
    """The flag that wins by ``PRECEDENCE`` among ``flags`` (``OK`` when empty)."""
    for q in PRECEDENCE:
        if q in flags:
            return q
    return Quality.OK


def usable(quality: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Boolean mask of channels whose quality is ``OK`` (the ones that may enter a fit)."""
    return np.asarray(quality, dtype=np.uint8) == np.uint8(Quality.OK)
