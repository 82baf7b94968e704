"""``python -m benchmarks model`` times the full FE and the reduced model in turns and reports the median of
the per-turn ratios (issue 15: a load change between the two sides no longer biases the speed-up)."""

from __future__ import annotations

import argparse
import statistics

import pytest

from benchmarks.model import _speed_figures
from model.fem import build_fe_model
from model.geometry import load_spindle
from model.rom import build_rom


@pytest.fixture(scope="module")
def coarse() -> tuple[object, object]:
    spec = load_spindle()
    fe = build_fe_model(spec, mesh_size_m=0.008)
    rom = build_rom(
        fe, spec, rank=8, n_train=2, n_check=1, check_steps=5, keep_per_sample=8, train_substeps=1
    )
    return fe, rom


def test_speed_up_is_the_median_of_the_per_turn_ratios(coarse: tuple[object, object]) -> None:
    fe, rom = coarse
    res = _speed_figures(fe, rom, argparse.Namespace(runs=3, seed=7))  # type: ignore[arg-type]
    turns = res["timing_turns"]
    full, batch, one = turns["full_ms"], turns["rom_ms_per_candidate"], turns["rom_single_ms"]
    assert len(full) == len(batch) == len(one) == 3
    assert min(full + batch + one) > 0.0
    assert res["full_forward_ms"] == statistics.median(full)
    assert res["rom_batched_ms_per_candidate"] == statistics.median(batch)
    assert res["rom_forward_ms"] == statistics.median(one)
    assert res["speedup_rom_vs_full"] == pytest.approx(
        statistics.median(f / b for f, b in zip(full, batch, strict=True))
    )
    assert res["speedup_rom_single_vs_full"] == pytest.approx(
        statistics.median(f / o for f, o in zip(full, one, strict=True))
    )
