"""One shaft-side channel (issue 40 part 5): the packaged spindle with one DAQ channel moved to the rear
pulley's rim, as a pyrometer aimed at it would read it (H1's zone, the shaft's rear end, which no packaged
channel sees).

The spindle TOML declares where each of the 32 channels sits, so a shop with such a pyrometer wires it to a
channel and declares it there: the product and the plant then see it like any other channel (the same noise
and offsets: a pyrometer's emissivity error is not modelled). Moving a channel, not adding a 33rd, keeps the
DAQ's register map; the channel it takes (a mid-housing one by default, 22: ``housing_10``, between two
others 22 mm away) is lost, so the gain measured is a lower bound of a 33rd channel's.
"""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path

__all__ = ["PULLEY_R_M", "PULLEY_Z_M", "pulley_spindle"]

PULLEY_R_M = 0.080  # the pulley's rim (model/data/spindle.toml, region "pulley": r 0.030-0.080 m)
PULLEY_Z_M = 0.030  # the middle of its width (z 0.005-0.055 m)


def pulley_spindle(channel: int, dest: Path) -> Path:
    """Write the packaged spindle TOML with ``channel`` (1-32) moved to the pulley's rim to ``dest`` (a
    directory) and return its path; ValueError when the channel is not in the file."""
    text = resources.files("model").joinpath("data/spindle.toml").read_text(encoding="utf-8")
    block = re.compile(
        rf"(\[\[sensors\]\]\nchannel = {int(channel)}\n)name = \"[^\"]*\"\nr_m = [0-9.]+\nz_m = [0-9.]+\n"
        rf"role = \"[a-z]+\"\n"
    )
    moved, n = block.subn(
        rf'\g<1>name = "rear_pulley_pyrometer"\nr_m = {PULLEY_R_M}\nz_m = {PULLEY_Z_M}\nrole = "housing"\n',
        text,
    )
    if n != 1:
        raise ValueError(f"--pulley-channel: channel {channel} not found in the packaged spindle TOML")
    path = dest / f"spindle_pulley_ch{int(channel)}.toml"
    path.write_text(moved, encoding="utf-8")
    return path
