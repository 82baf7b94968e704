"""The one mapping from DAQ status registers to per-channel quality flags (used by the Modbus driver and by
the recorded-log reader)."""

from __future__ import annotations

import numpy as np

from drivers.modbus_daq import channel_quality
from drivers.quality import Quality, from_daq_status, usable


def test_daq_status_codes_map_to_flags_and_unknown_codes_are_out_of_range() -> None:
    codes = np.array([[0, 1, 2], [7, -1, 0]])
    q = from_daq_status(codes)
    assert q.dtype == np.uint8 and q.shape == codes.shape
    assert [[Quality(int(x)) for x in row] for row in q] == [
        [Quality.OK, Quality.OPEN_CIRCUIT, Quality.OUT_OF_RANGE],
        [Quality.OUT_OF_RANGE, Quality.OUT_OF_RANGE, Quality.OK],
    ]
    np.testing.assert_array_equal(usable(q), codes == 0)


def test_the_driver_starts_from_the_same_mapping_before_its_own_checks() -> None:
    """Plausible values: the driver's flags are exactly the status mapping; a NaN value on a channel the DAQ
    calls ok is NAN, and an open circuit stays OPEN_CIRCUIT whatever it reads (``PRECEDENCE``)."""
    status = np.array([0, 1, 2, 5, 0])
    temps = np.array([25.0, 25.0, 25.0, 25.0, 25.0])
    np.testing.assert_array_equal(channel_quality(temps, status), from_daq_status(status))
    temps[[0, 1]] = np.nan
    q = channel_quality(temps, status)
    assert Quality(int(q[0])) is Quality.NAN and Quality(int(q[1])) is Quality.OPEN_CIRCUIT
