"""The virtual plant running a machining duty cycle without an end, computed chunk by chunk (``chtc demo``).

``EndlessPlant(spec, seed=...)`` takes its segments from ``simulator.duty.duty_cycle(seed)`` (at rest first,
then a new speed every 1–6 min) and runs ``model.plant.VirtualPlant`` over them ``chunk_s`` plant seconds at a
time, each chunk from the last one's final field (so the plant's state is continuous) with one seeded noise
generator (so a seed gives the same run, whatever the chunking's timing). ``next_chunk()`` computes the next
chunk (pure computation; run it in a thread) and ``append(chunk)`` publishes it: ``rows`` then holds every row
so far (the arrays of a ``model.plant.PlantRun`` plus the true H), replaced in one assignment.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from model.plant import Segment, VirtualPlant
from simulator.duty import duty_cycle

if TYPE_CHECKING:
    from model.fem import FEModel
    from model.geometry import SpindleSpec

__all__ = ["EndlessPlant", "PlantRows"]


@dataclass(frozen=True)
class PlantRows:
    """Plant rows (a ``drivers.sim.source.Timeline``): ``times_s`` s from the plant's start, measured
    ``temps_c`` °C (n, 32), ``ambient_c`` °C, ``speed_rpm`` rpm, ``torque_nm`` N·m, ``status`` (n, 32),
    and the true ``h_true`` (n, 7) W/(m²·K), which only a simulation knows."""

    times_s: NDArray[np.float64]
    temps_c: NDArray[np.float64]
    ambient_c: NDArray[np.float64]
    speed_rpm: NDArray[np.float64]
    torque_nm: NDArray[np.float64]
    status: NDArray[np.int64]
    h_true: NDArray[np.float64]

    def __add__(self, other: PlantRows) -> PlantRows:
        return PlantRows(
            **{
                name: np.concatenate([getattr(self, name), getattr(other, name)])
                for name in PlantRows.__dataclass_fields__
            }
        )


class EndlessPlant:
    """The seeded duty cycle played by the virtual plant, ``chunk_s`` plant seconds per chunk, no end.

    ``segments``: any endless iterator of ``Segment`` (default: ``duty_cycle(seed, idle_s=idle_s,
    segment_s=segment_s)``).
    ``fe``: the plant's FE model, shared by every chunk's plant (default: built once from ``spec``).
    """

    def __init__(
        self,
        spec: SpindleSpec,
        *,
        seed: int,
        chunk_s: float = 1800.0,
        dt_s: float = 10.0,
        idle_s: float = 300.0,
        segment_s: float | None = None,
        segments: Iterator[Segment] | None = None,
        fe: FEModel | None = None,
    ) -> None:
        if not chunk_s >= dt_s > 0:
            raise ValueError(f"chunk_s ({chunk_s}) must be >= dt_s ({dt_s}) > 0")
        self.spec, self.seed, self.chunk_s, self.dt_s = spec, seed, float(chunk_s), float(dt_s)
        self._segments = (
            segments if segments is not None else duty_cycle(seed, idle_s=idle_s, segment_s=segment_s)
        )
        self._rng = np.random.default_rng(seed)
        self._fe = fe if fe is not None else VirtualPlant(spec, seed=seed).fe
        self._field: NDArray[np.float64] | None = None  # the plant's field at the end of the last chunk
        self._end_s = 0.0  # plant time of the last chunk computed
        self._carry: Segment | None = None  # the rest of a segment cut at a chunk's end
        self.rows: PlantRows | None = None

    @property
    def end_s(self) -> float:
        """Plant time of the last row published, s (0 before the first chunk)."""
        return 0.0 if self.rows is None else float(self.rows.times_s[-1])

    def _take(self, seconds: float) -> list[Segment]:
        """The next segments covering exactly ``seconds`` (the last one cut, its rest kept for later)."""
        out: list[Segment] = []
        left = seconds
        while left > 1e-9:
            seg = self._carry if self._carry is not None else next(self._segments)
            self._carry = None
            if seg.duration_s > left + 1e-9:
                self._carry = Segment(seg.duration_s - left, seg.speed_rpm, seg.torque_nm, seg.ambient_c)
                seg = Segment(left, seg.speed_rpm, seg.torque_nm, seg.ambient_c)
            out.append(seg)
            left -= seg.duration_s
        return out

    def next_chunk(self) -> PlantRows:
        """Compute the next ``chunk_s`` of plant time (not published: pass it to :meth:`append`).

        Each chunk gets a fresh ``VirtualPlant`` on the shared FE model, so the factorisations of a chunk's
        conditions are dropped with it (the duty cycle's ambient drifts: few would be used again).
        """
        profile = self._take(self.chunk_s)
        plant = VirtualPlant(self.spec, seed=self.seed, fe=self._fe)
        t0 = profile[0].ambient_c if self._field is None else self._field
        run = plant.run(profile, dt_s=self.dt_s, t0_c=t0, rng=self._rng)
        first = 0 if self._field is None else 1  # row 0 repeats the previous chunk's last state
        self._field = run.final_field_c
        start = self._end_s
        self._end_s += float(run.times_s[-1])
        return PlantRows(
            times_s=run.times_s[first:] + start,
            temps_c=run.temps_c[first:],
            ambient_c=run.ambient_c[first:],
            speed_rpm=run.speed_rpm[first:],
            torque_nm=run.torque_nm[first:],
            status=run.status[first:],
            h_true=run.h_true[first:],
        )

    def append(self, chunk: PlantRows) -> None:
        """Publish ``chunk`` after the rows so far (one assignment)."""
        self.rows = chunk if self.rows is None else self.rows + chunk
