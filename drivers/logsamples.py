"""Recorded logs (temperature CSV + CAN log, ``drivers.logs``) -> acquisition samples, deterministically.

``samples_from_logs`` with ``period_s`` (what ``chtc identify`` uses) samples the recording as the live
acquisition of ``chtc replay`` does: one sample per ``acquisition.sample_period_s``, ``REPLAY_PHASE`` periods
after each grid point ``t_ref + k·period`` (``t_ref``: the earlier of the first row and the first CAN frame),
each showing the newest row at or before it. Without ``period_s`` each CSV row is one sample at its own time.
Speed and torque are those of the last decodable ``SpindleStatus`` frame at or before the sample, if it is at
most ``can_stale_s`` old and its status byte is not FAULT (else NaN with ``can_ok`` False, as the live
acquisition does), or a stated constant. DAQ status codes map to qualities (0 OK, 1 open circuit, 2 out of
range); a non-finite temperature is NAN. Unknown-ID, wrong-DLC or garbled frames are counted and skipped,
like the live CAN driver does. ``write_acquisition_csv`` writes the rows those samples show, one per period,
for ``chtc replay`` to serve (so both commands see the same data; docs/design/service.md).

A virtual plant's run gives its samples through ``simulator.plantsamples`` (the simulator's side).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from drivers.quality import Quality, from_daq_status
from drivers.ringbuffer import Sample

if TYPE_CHECKING:
    import can

    from drivers.logs import TemperatureLog

# The CAN state over a log: frame times (POSIX s), speed rpm, torque N·m, status ok (all (m,))
CanTrack = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]

__all__ = [
    "REPLAY_PHASE",
    "LogSamples",
    "acquisition_ticks",
    "samples_from_logs",
    "write_acquisition_csv",
]


REPLAY_PHASE = 0.5  # chtc replay's acquisition samples half a period after each grid point of the recording


@dataclass(kw_only=True)
class LogSamples:
    samples: list[Sample]
    rows: int
    frames: int
    bad_frames: int
    t_ref: float = 0.0  # POSIX s: the earlier of the first row and the first CAN frame


def _can_track(frames: list[can.Message]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
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


def acquisition_ticks(
    row_t_s: np.ndarray, t_ref: float, *, period_s: float, phase: float = REPLAY_PHASE
) -> tuple[np.ndarray, np.ndarray]:
    """The live acquisition's sample instants over a recording, and the row each one sees (pure).

    The acquisition samples once per ``period_s``; ``chtc replay`` starts it so that it samples ``phase``
    periods after each grid point ``t_ref + k·period_s`` (``service.commands.replay``). Each tick sees the
    newest row recorded at or before it; before the first row, the first row (as the replayed DAQ shows it
    from ``t_ref`` on). Ticks run while their grid point is not after the last row. Returns (ticks POSIX s,
    row index per tick).
    """
    if not period_s > 0 or not 0.0 <= phase < 1.0:
        raise ValueError(f"period_s must be > 0 and phase in [0, 1), got {period_s}, {phase}")
    n = int(np.floor((float(row_t_s[-1]) - t_ref) / period_s + 1e-9)) + 1
    grid = t_ref + period_s * np.arange(max(n, 1), dtype=float)
    ticks = grid + phase * period_s
    rows = np.clip(np.searchsorted(row_t_s, ticks, side="right") - 1, 0, len(row_t_s) - 1)
    return ticks, rows


def samples_from_logs(
    csv_path: str | Path,
    can_path: str | Path | None,
    *,
    period_s: float | None = None,
    phase: float = REPLAY_PHASE,
    can_stale_s: float = 1.0,
    speed_rpm: float | None = None,
    torque_nm: float | None = None,
) -> LogSamples:
    """Samples from a temperature CSV and (optionally) a CAN log; raises ``drivers.logs.LogFormatError``.

    ``period_s`` (the acquisition's ``sample_period_s``): one sample per period at the instants the live
    acquisition of ``chtc replay`` samples (``acquisition_ticks``), so that identify and replay see the same
    samples whatever the recording's row rate; None: one sample per CSV row at the row's time.
    ``speed_rpm``/``torque_nm``: a stated constant condition instead of a CAN log (both or neither).
    """
    from drivers.logs import read_can_log, read_temperature_csv

    stated = (speed_rpm, torque_nm)
    if (speed_rpm is None) != (torque_nm is None):
        raise ValueError("a stated condition needs both the speed (rpm) and the torque (N·m)")
    if can_path is not None and speed_rpm is not None:
        raise ValueError("give either a CAN log or a stated speed and torque, not both")
    log = read_temperature_csv(csv_path)
    frames = read_can_log(can_path) if can_path is not None else []
    ct, cs, cm, cok, bad = _can_track(frames)
    t_ref = min(float(log.t_s[0]), float(ct[0]) if ct.size else np.inf)
    if period_s is None:
        ticks, rows = np.asarray(log.t_s, dtype=float), np.arange(log.n_rows)
    else:
        ticks, rows = acquisition_ticks(
            np.asarray(log.t_s, dtype=float), t_ref, period_s=period_s, phase=phase
        )
    track = (ct, cs, cm, cok) if speed_rpm is None else None
    out = [
        _sample(log, int(k), t=float(t), track=track, stated=stated, can_stale_s=can_stale_s)
        for t, k in zip(ticks, rows, strict=True)
    ]
    return LogSamples(samples=out, rows=log.n_rows, frames=len(frames), bad_frames=bad, t_ref=t_ref)


def _sample(
    log: TemperatureLog,
    k: int,
    *,
    t: float,
    track: CanTrack | None,
    stated: tuple[float | None, float | None],
    can_stale_s: float,
) -> Sample:
    """Row ``k`` as the sample at time ``t``, with the CAN state then (or the stated speed and torque)."""
    if track is None:
        speed, torque, fresh = float(stated[0] or 0.0), float(stated[1] or 0.0), True
    else:
        ct, cs, cm, cok = track
        i = int(np.searchsorted(ct, t, side="right")) - 1
        fresh = i >= 0 and t - ct[i] <= can_stale_s and bool(cok[i])
        speed = float(cs[i]) if fresh else float("nan")
        torque = float(cm[i]) if fresh else float("nan")
    temps = np.asarray(log.temps_c[k], dtype=float)
    q = from_daq_status(log.status[k])
    q[~np.isfinite(temps)] = Quality.NAN
    return Sample(
        t=datetime.fromtimestamp(t, tz=UTC),
        temps_c=temps,
        ambient_c=float(log.ambient_c[k]),
        speed_rpm=speed,
        torque_nm=torque,
        quality=q,
        daq_ok=True,
        can_ok=fresh,
    )


def write_acquisition_csv(
    csv_path: str | Path,
    can_path: str | Path | None,
    out_path: str | Path,
    *,
    period_s: float,
    phase: float = REPLAY_PHASE,
) -> int:
    """The recording reduced to the rows the acquisition samples, one per period, each stamped at its grid
    point ``t_ref + k·period_s`` (``acquisition_ticks``); returns the number of rows written.

    ``chtc replay`` serves this file instead of the recording: its acquisition, sampling ``phase`` periods
    after each grid point, then sees exactly the row ``chtc identify`` uses, however dense and jittered the
    recorded rows are (a real-time recording has one row per second with receive-time jitter, and the
    acquisition polls the DAQ only once per ``modbus.poll_interval_s``, so it could see a row one earlier).
    The recorded DAQ counter of each row is kept.
    """
    from drivers.logs import TemperatureCsvWriter, read_can_log, read_temperature_csv

    log = read_temperature_csv(csv_path)
    frames = read_can_log(can_path) if can_path is not None else []
    first_frame = min((float(m.timestamp) for m in frames), default=np.inf)
    t_ref = min(float(log.t_s[0]), first_frame)
    ticks, rows = acquisition_ticks(np.asarray(log.t_s, dtype=float), t_ref, period_s=period_s, phase=phase)
    with TemperatureCsvWriter(out_path, n_channels=log.temps_c.shape[1]) as w:
        for t, k in zip(ticks - phase * period_s, rows, strict=True):
            w.write(
                datetime.fromtimestamp(float(t), tz=UTC),
                temps_c=log.temps_c[k],
                ambient_c=float(log.ambient_c[k]),
                status=log.status[k],
                counter=None if log.counter[k] < 0 else int(log.counter[k]),
            )
    return int(ticks.size)
