"""A thermal test (ISO 230-3 style) recorded on the virtual plant: the three files ``chtc commission growth``
reads, and the truth behind them.

The plant draws (or is given) its own mechanics (``model.plantmech``); its true nose growth comes from them
on its own mesh. The files are what a real test leaves: the DAQ's temperature CSV (``drivers.logs``), the
CAN log of ``SpindleStatus`` frames (every 0.5 s), and the displacement CSV (``time,axial_um,radial_um``,
UTC) of a capacitive sensor zeroed at the start, with its noise, a fixture offset, a slow drift and a few
missing readings.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from model.plant import Segment, VirtualPlant
from model.plantmech import PlantMechanics

__all__ = ["RECOMMENDED_PROFILE", "ThermalTest", "write_thermal_test"]

# heat-up in two speed steps, then a cool-down at rest (docs/commissioning.md, "The test profile")
RECOMMENDED_PROFILE: tuple[Segment, ...] = (
    Segment(duration_s=900.0, speed_rpm=0.0, torque_nm=0.0, ambient_c=21.0),
    Segment(duration_s=3600.0, speed_rpm=4000.0, torque_nm=5.0, ambient_c=21.0),
    Segment(duration_s=3600.0, speed_rpm=7000.0, torque_nm=5.0, ambient_c=21.0),
    Segment(duration_s=6300.0, speed_rpm=0.0, torque_nm=0.0, ambient_c=21.0),
)
CAN_PERIOD_S = 0.5


@dataclass(frozen=True)
class ThermalTest:
    """The files written and the truth: the plant's ``mechanics``, the true axial and radial growth [µm]
    at ``disp_t_s`` (epoch s) over the start, and the nuisances added."""

    temperatures: Path
    canlog: Path
    displacements: Path
    mechanics: PlantMechanics
    disp_t_s: np.ndarray
    axial_true_um: np.ndarray
    radial_true_um: np.ndarray
    offset_um: float
    drift_um_per_h: float


def write_thermal_test(
    out: Path,
    *,
    mechanics: PlantMechanics,
    profile: Sequence[Segment] = RECOMMENDED_PROFILE,
    seed: int = 0,
    start: datetime = datetime(2026, 11, 27, 6, 0, tzinfo=UTC),
    disp_every: int = 6,
    noise_um: float = 0.1,
    offset_um: float = 2.0,
    drift_um_per_h: float = 0.1,
    missing_every: int = 17,
    plant: VirtualPlant | None = None,
) -> ThermalTest:
    """Run ``profile`` on the plant (``mechanics``, seed ``seed``) and write ``out``/temperatures.csv,
    can.blf and displacements.csv; a displacement every ``disp_every`` samples (10 s each), every
    ``missing_every``-th one left empty."""
    import can

    from drivers.can_codec import encode_status
    from drivers.logs import TemperatureCsvWriter, write_can_log
    from model.geometry import load_spindle

    out.mkdir(parents=True, exist_ok=True)
    p = plant if plant is not None else VirtualPlant(load_spindle(), seed=seed, mechanics=mechanics)
    run = p.run(profile, keep_fields_every=disp_every, rng=np.random.default_rng([seed, 3]))
    t0 = start.timestamp()
    temps = out / "temperatures.csv"
    with TemperatureCsvWriter(temps) as w:
        for k, t in enumerate(run.times_s):
            w.write(
                datetime.fromtimestamp(t0 + float(t), tz=UTC),
                temps_c=run.temps_c[k],
                ambient_c=float(run.ambient_c[k]),
                status=run.status[k],
                counter=k,
            )
    frames = []
    n_frames = int(float(run.times_s[-1]) / CAN_PERIOD_S) + 1
    for i in range(n_frames):
        tc = i * CAN_PERIOD_S
        k = min(int(np.searchsorted(run.times_s, tc, side="right")) - 1, run.times_s.size - 1)
        data = encode_status(float(run.speed_rpm[k]), float(run.torque_nm[k]), i % 16, 0)
        frames.append(can.Message(timestamp=t0 + tc, arbitration_id=0x181, is_extended_id=False, data=data))
    canlog = out / "can.blf"
    write_can_log(canlog, frames)
    names = list(p.growth.names)
    g = p.growth_um(run.fields_c, float(run.fields_c[0].mean()))
    axial, radial = g[:, names.index("nose_axial")], g[:, names.index("nose_radial")]
    td = t0 + run.field_times_s
    rng = np.random.default_rng([seed, 5])
    hours = (td - td[0]) / 3600.0
    meas_a = axial + offset_um + drift_um_per_h * hours + rng.normal(0.0, noise_um, td.size)
    meas_r = radial + rng.normal(0.0, noise_um, td.size)
    disp = out / "displacements.csv"
    with disp.open("w", encoding="utf-8") as f:
        f.write("# ISO 230-3 style thermal test on the virtual plant (chtc commission growth)\n")
        f.write("time,axial_um,radial_um\n")
        for i, t in enumerate(td):
            stamp = datetime.fromtimestamp(float(t), tz=UTC) + timedelta(0)
            a = "" if missing_every and i % missing_every == missing_every - 1 else f"{meas_a[i]:.3f}"
            f.write(f"{stamp.isoformat().replace('+00:00', 'Z')},{a},{meas_r[i]:.3f}\n")
    return ThermalTest(
        temperatures=temps,
        canlog=canlog,
        displacements=disp,
        mechanics=mechanics,
        disp_t_s=td,
        axial_true_um=axial,
        radial_true_um=radial,
        offset_um=offset_um,
        drift_um_per_h=drift_um_per_h,
    )
