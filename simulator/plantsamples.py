"""A virtual-plant run -> acquisition samples (offline runs of the service core: demo, benchmarks, tests).

One sample per plant row, with the status-to-quality mapping of recorded logs (``drivers.logsamples``).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import TYPE_CHECKING

import numpy as np

from drivers.quality import from_daq_status
from drivers.ringbuffer import Sample

if TYPE_CHECKING:
    from model.plant import PlantRun

__all__ = ["samples_from_plant"]


def samples_from_plant(run: PlantRun, *, t0_s: float) -> list[Sample]:
    """One sample per row of a ``model.plant.PlantRun``, at UTC epoch ``t0_s`` + the row's plant time."""
    quality = from_daq_status(run.status)
    return [
        Sample(
            t=datetime.fromtimestamp(t0_s + float(t), tz=UTC),
            temps_c=np.asarray(run.temps_c[k], dtype=float),
            ambient_c=float(run.ambient_c[k]),
            speed_rpm=float(run.speed_rpm[k]),
            torque_nm=float(run.torque_nm[k]),
            quality=quality[k],
        )
        for k, t in enumerate(run.times_s)
    ]
