"""The demo's endless plant (``simulator.endless``): the duty cycle runs chunk after chunk with the plant's
state carried over (no jump at a chunk's seam), seeded, the speed changing every few minutes, no end."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from model.geometry import load_spindle
from model.plant import VirtualPlant
from simulator.duty import duty_cycle
from simulator.endless import EndlessPlant


@pytest.fixture(scope="module")
def plant_fe():  # type: ignore[no-untyped-def]
    return VirtualPlant(load_spindle(), seed=0).fe


def _rows(fe, seed: int, chunks: int, chunk_s: float = 900.0):  # type: ignore[no-untyped-def]
    p = EndlessPlant(load_spindle(), seed=seed, chunk_s=chunk_s, idle_s=120.0, fe=fe)
    for _ in range(chunks):
        p.append(p.next_chunk())
    return p.rows


@pytest.mark.slow  # about 10 s: 30 plant minutes on the plant's fine mesh
def test_chunks_join_without_a_seam_and_the_speed_keeps_changing(plant_fe) -> None:  # type: ignore[no-untyped-def]
    rows = _rows(plant_fe, seed=3, chunks=3, chunk_s=600.0)
    assert rows is not None
    t = rows.times_s
    np.testing.assert_allclose(np.diff(t), 10.0)  # one 10-s grid across the chunks
    assert t[0] == 0.0 and t[-1] == pytest.approx(3 * 600.0)
    # across each seam the sensors move like anywhere else (the plant's state is carried, not restarted:
    # a restart from the ambient would drop the warm sensors by degrees)
    truth = rows.temps_c
    steps = np.abs(np.diff(truth, axis=0)).max(axis=1)
    for seam in (60, 120):  # row index of the chunk ends
        assert steps[seam - 1 : seam + 1].max() < 1.0 + 5 * np.median(steps), steps[seam - 2 : seam + 2]
    assert truth[-1].max() > truth[0].max() + 2.0  # the spindle warms over the chunks
    assert rows.speed_rpm[:12].max() == 0.0  # at rest first
    speeds = [k for k, _ in itertools.groupby(rows.speed_rpm[12:])]
    assert len(speeds) >= 4 and max(speeds) <= 7000.0  # a new speed every 1-6 min over 28 min
    assert rows.h_true.shape == (t.size, 7)


def test_the_same_seed_gives_the_same_plant_and_another_seed_another_cycle(plant_fe) -> None:  # type: ignore[no-untyped-def]
    a, b = (_rows(plant_fe, seed=5, chunks=2, chunk_s=180.0) for _ in range(2))
    assert a is not None and b is not None
    np.testing.assert_array_equal(a.temps_c, b.temps_c)
    other = list(itertools.islice(duty_cycle(6, idle_s=120.0), 20))
    assert [s.speed_rpm for s in other] != [
        s.speed_rpm for s in itertools.islice(duty_cycle(5, idle_s=120.0), 20)
    ]


def test_duty_cycle_has_no_end() -> None:
    segs = list(itertools.islice(duty_cycle(1, idle_s=60.0), 500))
    assert len(segs) == 500 and segs[0].speed_rpm == 0.0
    assert all(a.speed_rpm != b.speed_rpm for a, b in itertools.pairwise(segs[1:]))
    assert {s.duration_s for s in segs[1:]} <= {60.0 * k for k in range(1, 7)}
