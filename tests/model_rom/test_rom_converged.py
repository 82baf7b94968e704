"""The served reduced model (defaults, service mesh) against the full FE converged in time, on the worst case
found while choosing the rank (issue 15, ``model.rom_check.error_report`` draws): a non-uniform start field
(the steady field of another H) followed by a jump of H, 10-min window."""

from __future__ import annotations

import numpy as np
import pytest

from model import rom_check
from model.fem import build_fe_model
from model.geometry import load_spindle
from model.rom import DEFAULT_RANK, DEFAULT_TRAIN_SUBSTEPS, load_or_build_rom
from service.settings import default_cache_dir


@pytest.mark.slow
def test_default_rom_is_within_0_012_c_of_a_converged_full_fe_after_a_start_field_jump() -> None:
    """Seed 777, fourth case of ``rom_check.error_report``'s draw: rank 46 trained on 10-s backward-Euler
    snapshots was 0.040 °C off here, rank 56 with those snapshots 0.019 °C; the default (56, snapshots at
    2.5 s) 0.009 °C. The reference's own error is ~0.005 °C, so the bar leaves it room.

    The reduced model is the one the service serves: read from the service's cache (built and saved there on a
    miss), whose key covers the FE matrices, the spindle, the build options and ``rom_cache.FORMAT_VERSION``
    (bumped when the training changes), as ``tests/service`` and ``tests/identify`` load it. Building it into
    a fresh directory here took ~33 of the test's ~39 s."""
    spec = load_spindle()
    fe = build_fe_model(spec)
    cache = default_cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    rom = load_or_build_rom(fe, spec, cache)
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
