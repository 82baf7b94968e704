"""The displacement CSV of a thermal test (``service.shell.commissioning.read_displacement_csv``): any rate,
missing values, comments; a bad file is one line naming the file, line and field, also through the CLI."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from service.cli import main as cli_main
from service.shell.commissioning import DisplacementFormatError, read_displacement_csv


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "disp.csv"
    p.write_text(text, encoding="utf-8")
    return p


def test_a_test_log_with_missing_values_any_rate_and_radial_reads(tmp_path: Path) -> None:
    p = _write(
        tmp_path,
        "# capacitive sensors, mandrel 40 mm\n"
        "time,axial_um,radial_um\n"
        "2026-11-27T08:00:00Z,0.10,0.0\n"
        "2026-11-27T08:00:00.5+00:00,,0.1\n"  # a missing axial reading, half a second later
        "2026-11-27T08:00:07Z,0.30,nan\n",
    )
    d = read_displacement_csv(p)
    assert np.allclose(d.t_s - d.t_s[0], [0.0, 0.5, 7.0])
    assert d.axial_um[0] == 0.10 and math.isnan(d.axial_um[1]) and d.axial_um[2] == 0.30
    assert d.radial_um is not None and math.isnan(d.radial_um[2])
    only_axial = read_displacement_csv(_write(tmp_path, "utc,axial_um\n2026-11-27T08:00:00Z,1.5\n"))
    assert only_axial.radial_um is None and only_axial.axial_um[0] == 1.5


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", r"empty file"),
        ("time,radial_um\n2026-11-27T08:00:00Z,1\n", r"disp\.csv:1: header: missing column 'axial_um'"),
        ("axial_um\n1.0\n", r"disp\.csv:1: header: no time column"),
        ("time,axial_um\n2026-11-27T08:00:00,1\n", r"disp\.csv:2: time: .* is not UTC"),
        ("time,axial_um\n2026-11-27T09:00:00+01:00,1\n", r"disp\.csv:2: time: .* is not UTC"),
        ("time,axial_um\n27.11.2026 08:00,1\n", r"disp\.csv:2: time: not an ISO-8601 time"),
        ("time,axial_um\n2026-11-27T08:00:00Z,1\n2026-11-27T08:00:01Z,1,2µm\n", None),
        ("time,axial_um\n2026-11-27T08:00:00Z,abc\n", r"disp\.csv:2: axial_um: not a number: 'abc'"),
        ("time,axial_um,radial_um\n2026-11-27T08:00:00Z,1\n", r"disp\.csv:2: expected 3 fields"),
        ("time,axial_um\n", r"no data rows"),
        ("time,axial_um\n2026-11-27T08:00:00Z,\n", r"axial_um: no value in any row"),
    ],
)
def test_a_bad_displacement_csv_names_the_line_and_field(
    tmp_path: Path, text: str, match: str | None
) -> None:
    p = _write(tmp_path, text)
    if match is None:  # extra trailing fields are tolerated (a sensor's status column)
        read_displacement_csv(p)
        return
    with pytest.raises(DisplacementFormatError, match=match):
        read_displacement_csv(p)


def test_the_cli_reports_a_bad_displacement_csv_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = Path(__file__).resolve().parents[2] / "service" / "data"
    p = _write(tmp_path, "time,radial_um\n2026-11-27T08:00:00Z,1\n")
    argv = [
        "commission",
        "growth",
        str(data / "example_temperatures.csv"),
        str(data / "example_can.blf"),
        str(p),
    ]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("chtc commission: ") and "missing column 'axial_um'" in err[0]
