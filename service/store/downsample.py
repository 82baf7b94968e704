"""1-minute means of the stored samples: what is kept after the raw samples are dropped (retention).

``MinuteMeans`` is a pure accumulator: ``add(sample)`` takes the samples in time order and returns the
previous minute's ``SampleMinuteData`` once a sample of a later minute arrives; ``flush()`` returns the
minute in progress. The buffered writer feeds it every sample it is given (``DbWriter(downsample=True)``), so
the means are written as the samples are, and the retention pass only has to drop raw data (no aggregation
at drop time). ``minute_means(samples)`` does the same over a list (the retention pass's backfill for raw
days stored before the means existed, ``chtc db merge``).

A minute cut by a restart is stored in two parts; the second is skipped (``ON CONFLICT DO NOTHING``): the
mean of the minute's first part is kept.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime

from service.contracts.records import SampleData, SampleMinuteData

__all__ = ["MinuteMeans", "SampleLike", "minute_means", "minute_of"]

MINUTE_S = 60


def minute_of(t: datetime) -> datetime:
    """The start of ``t``'s UTC minute."""
    return t.astimezone(UTC).replace(second=0, microsecond=0)


class SampleLike:
    """What the accumulator reads of a sample (``SampleData`` or a stored ``SampleRow``)."""

    t: datetime
    temps_c: Sequence[float | None]
    ambient_c: float | None
    speed_rpm: float | None
    torque_nm: float | None
    can_ok: bool
    daq_ok: bool


def _good(sample: SampleData | SampleLike) -> int:
    if isinstance(sample, SampleData):
        return sum(q == "ok" for q in sample.quality)
    return int(sample.n_good)  # type: ignore[attr-defined]


@dataclass
class _Minute:
    t: datetime
    n: int = 0
    sums: list[float] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)
    scalars: dict[str, list[float]] = field(default_factory=lambda: {"a": [], "s": [], "q": []})
    n_good_min: int = 1 << 30
    can_ok: bool = True
    daq_ok: bool = True

    def add(self, s: SampleData | SampleLike) -> None:
        temps = list(s.temps_c)
        if len(self.sums) < len(temps):
            self.sums += [0.0] * (len(temps) - len(self.sums))
            self.counts += [0] * (len(temps) - len(self.counts))
        for i, v in enumerate(temps):
            if v is not None and math.isfinite(v):
                self.sums[i] += float(v)
                self.counts[i] += 1
        for key, v in (("a", s.ambient_c), ("s", s.speed_rpm), ("q", s.torque_nm)):
            if v is not None and math.isfinite(v):
                self.scalars[key].append(float(v))
        self.n += 1
        self.n_good_min = min(self.n_good_min, _good(s))
        self.can_ok &= bool(s.can_ok)
        self.daq_ok &= bool(s.daq_ok)

    def record(self) -> SampleMinuteData:
        def mean(key: str) -> float | None:
            xs = self.scalars[key]
            return sum(xs) / len(xs) if xs else None

        speeds = self.scalars["s"]
        return SampleMinuteData(
            t=self.t,
            n=self.n,
            temps_c=[s / c if c else None for s, c in zip(self.sums, self.counts, strict=True)],
            ambient_c=mean("a"),
            speed_rpm=mean("s"),
            speed_max_rpm=max(speeds) if speeds else None,
            torque_nm=mean("q"),
            n_good_min=self.n_good_min,
            can_ok=self.can_ok,
            daq_ok=self.daq_ok,
        )


class MinuteMeans:
    """See the module docstring. A sample older than the minute in progress is ignored (counted)."""

    def __init__(self) -> None:
        self._minute: _Minute | None = None
        self.out_of_order = 0

    def add(self, sample: SampleData | SampleLike) -> SampleMinuteData | None:
        m = minute_of(sample.t)
        done = None
        if self._minute is not None and m != self._minute.t:
            if m < self._minute.t:
                self.out_of_order += 1
                return None
            done = self._minute.record()
            self._minute = None
        if self._minute is None:
            self._minute = _Minute(t=m)
        self._minute.add(sample)
        return done

    def flush(self) -> SampleMinuteData | None:
        done = None if self._minute is None else self._minute.record()
        self._minute = None
        return done


def minute_means(samples: Iterable[SampleData | SampleLike]) -> list[SampleMinuteData]:
    """The 1-minute means of ``samples`` (in time order)."""
    acc = MinuteMeans()
    out = [m for s in samples if (m := acc.add(s)) is not None]
    last = acc.flush()
    return [*out, last] if last is not None else out
