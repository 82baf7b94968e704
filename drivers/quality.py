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


def from_daq_status(status: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """Per-channel flags (uint8) from DAQ status registers: 0 ``OK``, 1 ``OPEN_CIRCUIT``, 2 ``OUT_OF_RANGE``.

    Any other code is reported as ``OUT_OF_RANGE`` (the device says "not ok" without saying why). The one
    mapping of the status codes: the Modbus driver and the recorded-log reader both use it.
    """
    codes = np.asarray(status, dtype=np.int64)
    out = np.full(codes.shape, np.uint8(Quality.OUT_OF_RANGE), dtype=np.uint8)
    out[codes == 0] = np.uint8(Quality.OK)
    out[codes == 1] = np.uint8(Quality.OPEN_CIRCUIT)
    return out


def usable(quality: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Boolean mask of channels whose quality is ``OK`` (the ones that may enter a fit)."""
    return np.asarray(quality, dtype=np.uint8) == np.uint8(Quality.OK)
