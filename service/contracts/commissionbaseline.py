"""The commissioning's offset baseline (issue 40 part 3): the sensor offsets taken during the thermal test's
initial rest, kept in the stored commissioning's report and used until the spindle rests again.

The ISO 230-3 test starts with the machine soaked at the room temperature and a 15-min rest
(docs/commissioning.md): the equilibrium an offset baseline needs. The service's own core, run over the test
(``service.shell.commissioning.field_history``), takes that baseline; ``commission_growth`` writes it into the
report (``baseline_entry``: ``"offset_baseline"``), so it is stored with the mechanics
(``mechanics_calibrations.report``, no table of its own). After a restart without a stored baseline (an empty
database, a spindle that is machining: no rest to take one) ``commissioning_baseline`` rebuilds it as a
``Calibration`` of source ``"commissioning"``, its 1σ widened by ``AGE_SD_C`` in quadrature: an RTD's or a
thermocouple's offset drifts slowly (a few hundredths of a °C over months), and a sensor exchanged since the
commissioning is not known here. The first rest baseline replaces it (``service.acquire.calibration``).

Errors: a stored entry that does not make a baseline raises ``RecordError`` naming the field.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Any

import numpy as np

from service.contracts.calibration import Calibration
from service.contracts.columns import finite_list
from service.contracts.errors import RecordError
from service.contracts.mechanics import MechanicsCalibration

__all__ = ["AGE_SD_C", "BASELINE_KEY", "COMMISSIONING", "baseline_entry", "commissioning_baseline"]

# 1σ [°C] added in quadrature to the commissioning baseline's own: the offsets' drift since the commissioning
# (RTDs and thermocouples drift a few hundredths of a °C a year; the rest baseline that follows replaces it)
AGE_SD_C = 0.05
BASELINE_KEY = "offset_baseline"  # the report's key (``CommissionReport.as_dict``)
COMMISSIONING = "commissioning"  # the ``Calibration.source`` of a baseline rebuilt from the commissioning


def baseline_entry(cal: Calibration | None) -> dict[str, Any] | None:
    """The report's ``offset_baseline``: offsets and 1σ per channel [°C] (null: no data), the rest window
    (ISO-8601 UTC) and its samples; None when the test gave no baseline."""
    if cal is None:
        return None
    return {
        "offsets_c": [None if v is None else round(v, 5) for v in finite_list(cal.offsets_c)],
        "sd_c": [None if v is None else round(v, 5) for v in finite_list(cal.sd_c)],
        "t_from": cal.t_from.isoformat(),
        "t_to": cal.t_to.isoformat(),
        "samples": int(cal.samples),
        "source": cal.source,
    }


def commissioning_baseline(
    mech: MechanicsCalibration | None, *, age_sd_c: float = AGE_SD_C
) -> Calibration | None:
    """The baseline of the commissioning's rest, source ``"commissioning"``, 1σ ⊕ ``age_sd_c``; None without a
    commissioning or when its report has no baseline (a report made before it was kept, a test without a
    rest). ``RecordError`` naming the field for an entry that is not a baseline."""
    entry = None if mech is None else mech.report.get(BASELINE_KEY)
    if entry is None:
        return None

    def bad(name: str, why: str) -> RecordError:
        return RecordError(f"mechanics report {BASELINE_KEY}.{name}: {why}")

    if not isinstance(entry, dict):
        raise bad("", f"expected an object, got {type(entry).__name__}")
    offsets = _floats(entry.get("offsets_c"), "offsets_c", bad)
    sd = _floats(entry.get("sd_c"), "sd_c", bad)
    if len(sd) != len(offsets) or not all(math.isfinite(v) and v >= 0.0 for v in sd):
        raise bad("sd_c", f"expected {len(offsets)} finite values >= 0 °C")
    try:
        t_from, t_to = (datetime.fromisoformat(str(entry[k])) for k in ("t_from", "t_to"))
        samples = int(entry["samples"])
    except (KeyError, TypeError, ValueError) as err:
        raise bad("t_from/t_to/samples", f"missing or not a time / count ({err})") from err
    return Calibration(
        offsets_c=np.asarray(offsets, dtype=float),
        sd_c=np.sqrt(np.asarray(sd, dtype=float) ** 2 + age_sd_c**2),
        t_from=t_from,
        t_to=t_to,
        samples=samples,
        source=COMMISSIONING,
    )


def _floats(values: object, name: str, bad: Any) -> list[float]:
    if not isinstance(values, list) or not values:
        raise bad(name, f"expected a list of per-channel values, got {type(values).__name__}")
    out = []
    for i, v in enumerate(values):
        if v is None:
            out.append(math.nan)
        elif isinstance(v, bool) or not isinstance(v, int | float):
            raise bad(name, f"channel {i + 1}: {v!r} is not a temperature in °C")
        else:
            out.append(float(v))
    return out
