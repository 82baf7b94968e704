"""The robustness bench's shaft-side channel (issue 40 part 5): one DAQ channel moved to a pyrometer's spot on
the shaft, the rest of the packaged spindle as it was."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.robustness.shaftchannel import SHAFT_SPOTS, shaft_spindle
from model.geometry import load_spindle


@pytest.mark.parametrize("spot", sorted(SHAFT_SPOTS))
def test_the_channel_moves_to_the_spot_and_nothing_else_changes(spot: str, tmp_path: Path) -> None:
    packaged = load_spindle(None)
    moved = load_spindle(str(shaft_spindle(22, spot, tmp_path)))
    name, r_m, z_m = SHAFT_SPOTS[spot]
    s = moved.sensors[21]
    assert (s.channel, s.name, s.r_m, s.z_m, s.role) == (22, name, r_m, z_m, "shaft")
    assert [x for i, x in enumerate(moved.sensors) if i != 21] == [
        x for i, x in enumerate(packaged.sensors) if i != 21
    ]
    assert moved.zones == packaged.zones and moved.regions == packaged.regions


def test_an_unknown_spot_or_channel_is_refused_naming_the_option(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--shaft-spot"):
        shaft_spindle(22, "drawbar", tmp_path)
    with pytest.raises(ValueError, match="--shaft-channel: channel 33"):
        shaft_spindle(33, "nose", tmp_path)
