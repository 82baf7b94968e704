"""The served reduced model (defaults, service mesh) against the full FE converged in time, on the worst case
found while choosing the rank (issue 15, ``model.rom_check.error_report`` draws): a non-uniform start field
(the steady field of another H) followed by a jump of H, 10-min window."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from model import rom_check
from model.fem import build_fe_model
from model.geometry import load_spindle
from model.rom import DEFAULT_RANK, DEFAULT_TRAIN_SUBSTEPS, load_or_build_rom


@pytest.mark.slow
def test_default_rom_is_within_0_012_c_of_a_converged_full_fe_after_a_start_field_jump(
    tmp_path: Path,
) -> None:
    """Seed 777, fourth case of ``rom_check.error_report``'s draw: rank 46 trained on 10-s backward-Euler
    snapshots was 0.040 °C off here, rank 56 with those snapshots 0.019 °C; the default (56, snapshots at
    2.5 s) 0.009 °C. The reference's own error is ~0.005 °C, so the bar leaves it room."""
    spec = load_spindle()
    fe = build_fe_model(spec)
    rom = load_or_build_rom(fe, spec, tmp_path)
    assert (rom.rank, rom.substeps) == (DEFAULT_RANK, 0) and DEFAULT_TRAIN_SUBSTEPS > 1
    rng = np.random.default_rng(777)
    for i in range(4):  # the same draws as error_report(seed=777, n_steps=60)
        case = rom_check.random_case(
            fe, rng, box=rom.h_box, n_steps=60, dt_s=10.0, q_max_w=(300.0, 150.0), log_h=i % 2 == 0
        )
    full, ref_err = rom_check.case_reference(fe, case, theta=rom.theta, ref_substeps=20)
    assert ref_err < 0.006
    errors = rom_check.rom_errors(rom, case, full)
    assert errors.max() <= 0.012, errors
