"""One shaft-side channel (issue 40 part 5): the packaged spindle with one DAQ channel moved to the shaft, as
a pyrometer aimed at it would read it: at the rear pulley's rim (H1's zone) or at the shaft nose (H5's zone,
the front shoulder beyond the front end cap), parts no packaged channel sees.

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

__all__ = ["SHAFT_SPOTS", "shaft_spindle"]

# name, r [m], z [m] (model/data/spindle.toml: region "pulley" r 0.030-0.080, z 0.005-0.055; "shaft_nose"
# r 0-0.055, z 0.560-0.610)
SHAFT_SPOTS: dict[str, tuple[str, float, float]] = {
    "pulley": ("rear_pulley_pyrometer", 0.080, 0.030),
    "nose": ("shaft_nose_pyrometer", 0.055, 0.585),
}


def shaft_spindle(channel: int, spot: str, dest: Path) -> Path:
    """Write the packaged spindle TOML with ``channel`` (1-32) moved to ``spot`` (``SHAFT_SPOTS``) to
    ``dest`` (a directory) and return its path; ValueError naming the option when either is unknown."""
    if spot not in SHAFT_SPOTS:
        raise ValueError(f"--shaft-spot: must be one of {sorted(SHAFT_SPOTS)}, got {spot!r}")
    name, r_m, z_m = SHAFT_SPOTS[spot]
    text = resources.files("model").joinpath("data/spindle.toml").read_text(encoding="utf-8")
    block = re.compile(
        rf"(\[\[sensors\]\]\nchannel = {int(channel)}\n)name = \"[^\"]*\"\nr_m = [0-9.]+\nz_m = [0-9.]+\n"
        rf"role = \"[a-z]+\"\n"
    )
    moved, n = block.subn(rf'\g<1>name = "{name}"\nr_m = {r_m}\nz_m = {z_m}\nrole = "shaft"\n', text)
    if n != 1:
        raise ValueError(f"--shaft-channel: channel {channel} not found in the packaged spindle TOML")
    path = dest / f"spindle_{spot}_ch{int(channel)}.toml"
    path.write_text(moved, encoding="utf-8")
    return path
