"""Recorded logs (temperature CSV + CAN log, ``drivers.logs``) or a virtual-plant run -> acquisition samples,
deterministically.

Each CSV row becomes one ``drivers.ringbuffer.Sample`` at the row's UTC time. Speed and torque are those of
the last decodable ``SpindleStatus`` frame at or before the row, if it is at most ``can_stale_s`` old and its
status byte is not FAULT (else NaN with ``can_ok`` False, as the live acquisition does). DAQ status codes map
to qualities (0 OK, 1 open circuit, 2 out of range); a non-finite temperature is NAN. Unknown-ID, wrong-DLC
or garbled frames are counted and skipped, like the live CAN driver does.

``samples_from_plant`` turns a ``model.plant.PlantRun`` into one sample per plant row (offline runs of the
service core: benchmarks, tests), with the same status-to-quality mapping.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["LogSamples", "samples_from_logs", "samples_from_plant"]


@dataclass
class LogSamples:
    samples: list[Any]
    rows: int
    frames: int
    bad_frames: int


def _quality(status: Any) -> np.ndarray:
    """DAQ status codes (0 ok, 1 open circuit, 2 out of range; anything else out of range) -> ``Quality``."""
    from drivers.quality import Quality

    codes = np.asarray(status, dtype=np.int64)
    q = np.full(codes.shape, Quality.OUT_OF_RANGE, dtype=np.uint8)
    q[codes == 0] = Quality.OK
    q[codes == 1] = Quality.OPEN_CIRCUIT
    return q


def _can_track(frames: list[Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    from drivers.can_codec import SensorStatus, decode_frame
    from drivers.errors import FrameError

    t, speed, torque, ok, bad = [], [], [], [], 0
    for msg in frames:
        try:
            st = decode_frame(msg.arbitration_id, bytes(msg.data), is_extended_id=msg.is_extended_id)
        except FrameError:
            bad += 1
            continue
        t.append(float(msg.timestamp))
        speed.append(st.speed_rpm)
        torque.append(st.torque_nm)
        ok.append(st.status is not SensorStatus.FAULT)
    return np.array(t), np.array(speed), np.array(torque), np.array(ok, dtype=bool), bad


def samples_from_logs(
    csv_path: str | Path, can_path: str | Path | None, *, can_stale_s: float = 1.0
) -> LogSamples:
    """Samples from a temperature CSV and (optionally) a CAN log; raises ``drivers.logs.LogFormatError``."""
    from drivers.logs import read_can_log, read_temperature_csv
    from drivers.quality import Quality
    from drivers.ringbuffer import Sample

    log = read_temperature_csv(csv_path)
    frames = read_can_log(can_path) if can_path is not None else []
    ct, cs, cm, cok, bad = _can_track(frames)
    out = []
    for k in range(log.n_rows):
        t = float(log.t_s[k])
        i = int(np.searchsorted(ct, t, side="right")) - 1
        fresh = i >= 0 and t - ct[i] <= can_stale_s and bool(cok[i])
        temps = np.asarray(log.temps_c[k], dtype=float)
        q = _quality(log.status[k])
        q[~np.isfinite(temps)] = Quality.NAN
        out.append(
            Sample(
                t=datetime.fromtimestamp(t, tz=UTC),
                temps_c=temps,
                ambient_c=float(log.ambient_c[k]),
                speed_rpm=float(cs[i]) if fresh else float("nan"),
                torque_nm=float(cm[i]) if fresh else float("nan"),
                quality=q,
                daq_ok=True,
                can_ok=fresh,
            )
        )
    return LogSamples(out, log.n_rows, len(frames), bad)


def samples_from_plant(run: Any, *, t0_s: float) -> list[Any]:
    """One sample per row of a ``model.plant.PlantRun``, at UTC epoch ``t0_s`` + the row's plant time."""
    from drivers.ringbuffer import Sample

    quality = _quality(run.status)
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
