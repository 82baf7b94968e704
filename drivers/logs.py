"""Recorded logs: temperatures as CSV, CAN traffic as any python-can log format.

**Temperature CSV** (one row per DAQ sample, ``\\n`` line ends, every line terminated)::

    timestamp_utc,counter,ambient_c,ch01_c,...,ch32_c,st01,...,st32
    2026-11-22T04:30:00.100000+00:00,17,20.5,21.03,...,nan,...,0,...,1

- ``timestamp_utc``: ISO-8601 with a UTC offset (``+00:00`` or ``Z``); naive timestamps are rejected;
- ``counter``: the DAQ sample counter (uint32), empty when unknown;
- ``ambient_c`` and ``chNN_c``: °C, ``nan`` for a missing value;
- ``stNN``: DAQ per-channel status (0 ok, 1 open circuit, 2 out of range).

The channel count is read from the header (``ch01_c``.. consecutive, matching ``st01``..). Timestamps must not
go backwards.

**CAN logs**: ``.asc``, ``.blf``, ``.log`` (candump), ``.csv``, ``.trc`` (PCAN-View trace) and ``.mf4`` (ASAM
MDF 4, needs the optional ``asammdf`` package: ``pip install spindle-chtc[mf4]``) through
``can.Logger``/``can.LogReader``, with absolute (epoch) timestamps so that they line up with the CSV. Readers
validate each frame and detect truncation where the format allows it (BLF header size, ASC end marker, a
partial last line of ASC/TRC/candump, an MF4 file cut short); ASC and TRC lines python-can would skip are
refused, naming the frame.

Errors::

    DriverError
    └── LogFormatError(DriverError, ValueError)   .path, .line (CSV, 1-based) or .frame (CAN, 1-based)
"""

from __future__ import annotations

import copy
import csv
import io
import math
import os
import re
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

import can
import numpy as np
from numpy.typing import ArrayLike, NDArray

from drivers.errors import DriverError

__all__ = [
    "CAN_LOG_SUFFIXES",
    "CanLogWriter",
    "LogFormatError",
    "TemperatureCsvWriter",
    "TemperatureLog",
    "TemperatureRow",
    "csv_header",
    "iter_can_log",
    "iter_temperature_csv",
    "read_can_log",
    "read_temperature_csv",
    "write_can_log",
]

CAN_LOG_SUFFIXES: tuple[str, ...] = (".asc", ".blf", ".log", ".csv", ".trc", ".mf4")
_BACKWARDS_TOLERANCE_S = 1e-3


class LogFormatError(DriverError, ValueError):
    """A log file is corrupt, truncated or not in the expected format; names the file and line or frame."""

    def __init__(self, message: str, *, path: str | Path, line: int | None = None, frame: int | None = None):
        where = f", line {line}" if line is not None else f", frame {frame}" if frame is not None else ""
        super().__init__(f"{path}{where}: {message}")
        self.path = Path(path)
        self.line = line
        self.frame = frame


def csv_header(n_channels: int = 32) -> list[str]:
    """The temperature CSV header for ``n_channels`` channels."""
    chans = [f"ch{i:02d}_c" for i in range(1, n_channels + 1)]
    stats = [f"st{i:02d}" for i in range(1, n_channels + 1)]
    return ["timestamp_utc", "counter", "ambient_c", *chans, *stats]


@dataclass(frozen=True)
class TemperatureRow:
    """One CSV row: UTC time, DAQ counter (or None), ambient °C, temperatures °C (n,), status codes (n,)."""

    t: datetime
    counter: int | None
    ambient_c: float
    temps_c: NDArray[np.float64]
    status: NDArray[np.int64]


@dataclass(frozen=True)
class TemperatureLog:
    """A whole temperature CSV as arrays; ``t_s`` is POSIX seconds (UTC), ``counter`` is -1 when unknown."""

    path: Path
    t_s: NDArray[np.float64]
    counter: NDArray[np.int64]
    ambient_c: NDArray[np.float64]
    temps_c: NDArray[np.float64]
    status: NDArray[np.int64]

    @property
    def n_rows(self) -> int:
        """Number of samples."""
        return int(self.t_s.size)

    def timestamps(self) -> list[datetime]:
        """The row times as UTC datetimes."""
        return [datetime.fromtimestamp(t, tz=UTC) for t in self.t_s]


class TemperatureCsvWriter:
    """Writes the temperature CSV, one flushed line per :meth:`write`; use as a context manager."""

    def __init__(self, path: str | Path, *, n_channels: int = 32) -> None:
        self.path = Path(path)
        self.n_channels = n_channels
        self._file = self.path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(csv_header(n_channels))
        self.rows_written = 0

    def write(
        self,
        t: datetime,
        *,
        temps_c: ArrayLike,
        ambient_c: float,
        status: ArrayLike | None = None,
        counter: int | None = None,
    ) -> None:
        """Append one sample taken at UTC time ``t`` (temperatures °C, status codes 0/1/2, counter)."""
        if t.tzinfo is None:
            raise ValueError("t: a timezone-aware UTC datetime is required")
        temps = np.asarray(temps_c, dtype=float).reshape(-1)
        stat = np.zeros(self.n_channels, dtype=int) if status is None else np.asarray(status).reshape(-1)
        if temps.size != self.n_channels or stat.size != self.n_channels:
            raise ValueError(
                f"temps_c/status: expected {self.n_channels} values, got {temps.size}/{stat.size}"
            )
        row = [t.astimezone(UTC).isoformat(), "" if counter is None else str(int(counter)), _fmt(ambient_c)]
        row += [_fmt(v) for v in temps] + [str(int(s)) for s in stat]
        self._writer.writerow(row)
        self._file.flush()
        self.rows_written += 1

    def close(self) -> None:
        """Close the file."""
        self._file.close()

    def __enter__(self) -> TemperatureCsvWriter:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _fmt(value: float) -> str:
    v = float(value)
    return "nan" if math.isnan(v) else repr(v)


def iter_temperature_csv(path: str | Path) -> Iterator[TemperatureRow]:
    """Yield the rows of a temperature CSV, validating each; raise :class:`LogFormatError` naming the line."""
    path = Path(path)
    try:
        with path.open("r", newline="", encoding="utf-8") as f:
            yield from _iter_lines(path, f)
    except (OSError, UnicodeDecodeError) as err:
        raise LogFormatError(f"cannot read: {err}", path=path) from err


def _iter_lines(path: Path, f: io.TextIOBase) -> Iterator[TemperatureRow]:
    header_line = f.readline()
    if not header_line:
        raise LogFormatError("empty file (no header)", path=path, line=1)
    n = _check_header(path, _split(path, header_line, 1))
    last_t: float | None = None
    for lineno, text in enumerate(f, start=2):
        if not text.endswith("\n"):
            raise LogFormatError("last line has no line end (file truncated?)", path=path, line=lineno)
        if not text.strip():
            continue
        row = _parse_row(path, lineno, _split(path, text, lineno), n)
        t = row.t.timestamp()
        if last_t is not None and t < last_t:
            raise LogFormatError("timestamp goes backwards", path=path, line=lineno)
        last_t = t
        yield row


def _split(path: Path, text: str, lineno: int) -> list[str]:
    try:
        return next(csv.reader([text]))
    except (csv.Error, StopIteration) as err:
        raise LogFormatError(f"not CSV: {err}", path=path, line=lineno) from err


def _check_header(path: Path, fields: list[str]) -> int:
    if len(fields) < 5 or (len(fields) - 3) % 2:
        raise LogFormatError(
            f"bad header ({len(fields)} columns), expected {csv_header()[:3]}...", path=path, line=1
        )
    n = (len(fields) - 3) // 2
    for i, (got, want) in enumerate(zip(fields, csv_header(n), strict=True), start=1):
        if got.strip() != want:
            raise LogFormatError(f"header column {i} is {got!r}, expected {want!r}", path=path, line=1)
    return n


def _parse_row(path: Path, lineno: int, fields: list[str], n: int) -> TemperatureRow:
    if len(fields) != 3 + 2 * n:
        raise LogFormatError(f"expected {3 + 2 * n} fields, got {len(fields)}", path=path, line=lineno)
    names = csv_header(n)
    values = [_float(path, lineno, names[k], fields[k]) for k in range(2, 3 + n)]
    status = [_status(path, lineno, names[k], fields[k]) for k in range(3 + n, 3 + 2 * n)]
    return TemperatureRow(
        t=_timestamp(path, lineno, fields[0]),
        counter=_counter(path, lineno, fields[1]),
        ambient_c=values[0],
        temps_c=np.array(values[1:], dtype=float),
        status=np.array(status, dtype=np.int64),
    )


def _timestamp(path: Path, lineno: int, text: str) -> datetime:
    try:
        t = datetime.fromisoformat(text.strip())
    except ValueError as err:
        raise LogFormatError(f"timestamp_utc: not ISO-8601: {text!r}", path=path, line=lineno) from err
    if t.tzinfo is None:
        raise LogFormatError(f"timestamp_utc: no UTC offset in {text!r}", path=path, line=lineno)
    return t.astimezone(UTC)


def _counter(path: Path, lineno: int, text: str) -> int | None:
    if not text.strip():
        return None
    try:
        value = int(text)
    except ValueError as err:
        raise LogFormatError(f"counter: not an integer: {text!r}", path=path, line=lineno) from err
    if not 0 <= value < 2**32:
        raise LogFormatError(f"counter: {value} outside uint32", path=path, line=lineno)
    return value


def _float(path: Path, lineno: int, name: str, text: str) -> float:
    try:
        return float(text)
    except ValueError as err:
        raise LogFormatError(f"{name}: not a number: {text!r}", path=path, line=lineno) from err


def _status(path: Path, lineno: int, name: str, text: str) -> int:
    if text.strip() not in ("0", "1", "2"):
        raise LogFormatError(f"{name}: status must be 0, 1 or 2, got {text!r}", path=path, line=lineno)
    return int(text)


def read_temperature_csv(path: str | Path) -> TemperatureLog:
    """Read and validate a whole temperature CSV into arrays (see :class:`TemperatureLog`)."""
    rows = list(iter_temperature_csv(path))
    if not rows:
        raise LogFormatError("no data rows", path=path, line=2)
    return TemperatureLog(
        path=Path(path),
        t_s=np.array([r.t.timestamp() for r in rows], dtype=float),
        counter=np.array([-1 if r.counter is None else r.counter for r in rows], dtype=np.int64),
        ambient_c=np.array([r.ambient_c for r in rows], dtype=float),
        temps_c=np.vstack([r.temps_c for r in rows]),
        status=np.vstack([r.status for r in rows]),
    )


# ----------------------------------------------------------------------------------------------- CAN logs


def _check_suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in CAN_LOG_SUFFIXES:
        raise LogFormatError(
            f"unsupported CAN log format {suffix!r}, use one of {CAN_LOG_SUFFIXES}", path=path
        )
    return suffix


class CanLogWriter:
    """Writes CAN frames to a python-can log file chosen by suffix (.asc, .blf, .log, .csv, .trc, .mf4)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        _check_suffix(self.path)
        _check_mf4_support(self.path)
        try:
            self._logger: Any = can.Logger(str(self.path))
        except (OSError, ValueError) as err:
            raise LogFormatError(f"cannot open CAN log for writing: {err}", path=self.path) from err
        self.frames_written = 0

    def write(self, msg: can.Message) -> None:
        """Append one frame (its ``timestamp`` must be POSIX seconds, UTC).

        A channel name that is not a small number (e.g. a virtual bus called ``sim-3f9a``, or a remote URL)
        is not stored: BLF and ASC keep channels as integers.
        """
        try:
            self._logger.on_message_received(_portable_channel(msg))
        except (struct.error, ValueError, OSError) as err:
            raise LogFormatError(
                f"cannot write: {err}", path=self.path, frame=self.frames_written + 1
            ) from err
        self.frames_written += 1

    def close(self) -> None:
        """Flush and close the file (BLF writes its header, ASC its end marker, here)."""
        self._logger.stop()

    def __enter__(self) -> CanLogWriter:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _portable_channel(msg: can.Message) -> can.Message:
    if msg.channel is None or (isinstance(msg.channel, int) and 0 <= msg.channel <= 255):
        return msg
    number = can.util.channel2int(msg.channel)
    out = copy.copy(msg)
    out.channel = number if number is not None and 0 <= number <= 255 else None
    return out


def iter_can_log(path: str | Path) -> Iterator[can.Message]:
    """Yield the frames of a CAN log with absolute timestamps, validating each.

    Raises :class:`LogFormatError` naming the 1-based frame at which the file is corrupt or truncated
    (i.e. the first frame that could not be read), or a frame that is itself invalid.
    """
    path = Path(path)
    suffix = _check_suffix(path)
    if not path.is_file():
        raise LogFormatError("no such file", path=path)
    _check_mf4_support(path)
    if suffix == ".asc":
        _check_asc_lines(path)
    if suffix == ".trc":
        _check_trc_lines(path)
    count = 0
    last_t = -math.inf
    try:
        reader: Any = can.LogReader(str(path), **({"relative_timestamp": False} if suffix == ".asc" else {}))
        with reader:
            for msg in reader:
                count += 1
                _check_frame(path, count, msg, last_t)
                last_t = max(last_t, msg.timestamp)
                yield msg
    except LogFormatError:
        raise
    except Exception as err:  # the readers raise ValueError, binascii.Error, struct.error, BLFParseError ...
        raise LogFormatError(f"unreadable ({type(err).__name__}: {err})", path=path, frame=count + 1) from err
    _check_complete(path, suffix, count, reader)


def _check_complete(path: Path, suffix: str, count: int, reader: Any) -> None:
    if suffix == ".blf":
        declared = int(getattr(reader, "file_size", 0))
        actual = os.path.getsize(path)
        if declared and actual < declared:
            raise LogFormatError(
                f"truncated after {count} frames: header declares {declared} bytes, file has {actual}",
                path=path,
                frame=count + 1,
            )
    if suffix == ".asc":
        with path.open("rb") as f:
            f.seek(max(0, os.path.getsize(path) - 64))
            tail = f.read().decode("ascii", "replace").strip().lower()
        if not tail.endswith("end triggerblock"):
            raise LogFormatError("truncated: no 'End TriggerBlock' line", path=path, frame=count + 1)


_ASC_EVENT = re.compile(r"^\s*\d+\.\d+\s+\S")
_ASC_FRAME = re.compile(r"^\s*\d+\.\d+\s+\d+\s+[0-9A-Fa-f]+x?\s+(Rx|Tx)\s", re.IGNORECASE)


def _check_asc_lines(path: Path) -> None:
    """python-can's ASC reader skips lines it does not understand; refuse them instead (names the frame)."""
    inside, frames = False, 0
    with path.open("r", encoding="ascii", errors="replace") as f:
        for lineno, text in enumerate(f, start=1):
            low = text.strip().lower()
            if low.startswith("begin triggerblock"):
                inside = True
            elif low.startswith("end triggerblock"):
                inside = False
            elif inside and low and not low.startswith("//"):
                if not _ASC_EVENT.match(text):
                    raise LogFormatError(
                        f"unparseable ASC line {lineno}: {text.strip()[:40]!r}", path=path, frame=frames + 1
                    )
                frames += bool(_ASC_FRAME.match(text))


def _check_mf4_support(path: Path) -> None:
    if path.suffix.lower() != ".mf4":
        return
    try:
        import asammdf  # noqa: F401  (optional dependency, only for .mf4)
    except ImportError as err:
        raise LogFormatError(
            "MF4 logs need the optional package asammdf (pip install 'spindle-chtc[mf4]')", path=path
        ) from err


_TRC_FRAME = re.compile(r"^\s*\d+\)?\s+-?\d+(\.\d+)?\s+\S")


def _check_trc_lines(path: Path) -> None:
    """python-can's TRC reader skips lines it does not understand and reads a line cut short as a shorter
    frame; refuse both instead (names the frame). TRC has no end marker: a file cut exactly at a line end
    reads as a shorter log."""
    frames = 0
    with path.open("r", encoding="ascii", errors="replace") as f:
        for lineno, text in enumerate(f, start=1):
            stripped = text.strip()
            if not stripped or stripped.startswith(";"):
                continue
            frames += 1
            if not _TRC_FRAME.match(text):
                raise LogFormatError(
                    f"unparseable TRC line {lineno}: {stripped[:40]!r}", path=path, frame=frames
                )
            if not text.endswith("\n"):
                raise LogFormatError(f"truncated: TRC line {lineno} is cut short", path=path, frame=frames)


def _check_frame(path: Path, index: int, msg: can.Message, last_t: float) -> None:
    if not math.isfinite(msg.timestamp):
        raise LogFormatError("timestamp is not finite", path=path, frame=index)
    if msg.timestamp < last_t - _BACKWARDS_TOLERANCE_S:
        raise LogFormatError(
            f"timestamp goes backwards ({msg.timestamp:.6f} < {last_t:.6f})", path=path, frame=index
        )
    if not msg.is_remote_frame and not msg.is_error_frame and msg.dlc != len(msg.data):
        raise LogFormatError(f"DLC {msg.dlc} but {len(msg.data)} data bytes", path=path, frame=index)
    limit = 0x1FFFFFFF if msg.is_extended_id else 0x7FF
    if not 0 <= msg.arbitration_id <= limit:
        raise LogFormatError(f"arbitration ID 0x{msg.arbitration_id:X} out of range", path=path, frame=index)


def read_can_log(path: str | Path) -> list[can.Message]:
    """Read and validate a whole CAN log (see :func:`iter_can_log`)."""
    return list(iter_can_log(path))


def write_can_log(path: str | Path, messages: Sequence[can.Message]) -> int:
    """Write ``messages`` to a CAN log; returns the number of frames written."""
    with CanLogWriter(path) as writer:
        for msg in messages:
            writer.write(msg)
        return writer.frames_written
