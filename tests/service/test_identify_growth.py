"""``chtc identify --json``: the growth history (per identification, the growth at its window end as
``/compensation`` would have served it), on the shipped example recording (docs/design/growth.md)."""

from __future__ import annotations

import itertools
import json
from datetime import datetime
from pathlib import Path

import pytest

from service.cli import main as cli_main

pytestmark = pytest.mark.slow  # chtc identify over the example recording (~13 s at load 8)

DATA = Path(__file__).resolve().parents[2] / "service" / "data"


def test_identify_json_carries_the_growth_at_each_identifications_end(tmp_path: Path) -> None:
    out = tmp_path / "example.json"
    argv = ["identify", str(DATA / "example_temperatures.csv"), str(DATA / "example_can.blf")]
    assert cli_main([*argv, "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    ok = [r for r in rows if r["outcome"] == "ok"]
    assert len(ok) >= 2 and all(r["growth"] is None for r in rows if r["outcome"] != "ok")
    refs = {r["growth"]["t_ref_c"] for r in ok}
    assert len(refs) == 1 and 21.0 < refs.pop() < 23.0  # the cold start (22 °C ambient), one reference
    axial, std = [], []
    for r in ok:
        g = r["growth"]
        assert datetime.fromisoformat(g["at"]) == datetime.fromisoformat(r["window_to"])
        for part in ("axial", "radial", "steady_axial"):
            v = g[part]
            assert v["plc_0p1um"] == round(10 * v["um"]), part
            assert v["ci95_um"][0] < v["um"] < v["ci95_um"][1], part
        axial.append(g["axial"]["um"])
        lo, hi = g["axial"]["ci95_um"]
        std.append((hi - lo) / (2 * 1.96))
    # 3000 then 4000 rpm from cold: the nose keeps growing towards the tool, up to the filtered field's own
    # noise near the end (measured 4.6915 then 4.6859 µm; the served 1σ 0.13 and 1.1 µm)
    assert axial[0] > 0 and all(
        b > a - 2.0 * sd for (a, b), sd in zip(itertools.pairwise(axial), std[1:], strict=True)
    ), (axial, std)
    assert axial[-1] > axial[0]
