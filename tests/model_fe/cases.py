"""Small hand-made spindle descriptions for the model_fe tests."""

from __future__ import annotations

import copy
import tomllib
from typing import Any

from model.geometry import PACKAGED_SPEC

A_M, B_M, L_M = 0.02, 0.05, 0.1  # hollow cylinder: inner radius, outer radius, length


def packaged_doc() -> dict[str, Any]:
    """The packaged spindle TOML as a dict (a fresh copy)."""
    with PACKAGED_SPEC.open("rb") as fh:
        return copy.deepcopy(tomllib.load(fh))


def _zone(name: str, segments: list[list[list[float]]]) -> dict[str, Any]:
    return {
        "name": name,
        "side": "ambient",
        "rotating": False,
        "radius_m": B_M,
        "diameter_m": 2 * B_M,
        "length_m": 2 * B_M,
        "segments": segments,
    }


def cylinder_doc(k: float = 40.0, rho: float = 7800.0, c: float = 460.0) -> dict[str, Any]:
    """A hollow cylinder r in [A, B], z in [0, L], made of two stacked heated halves.

    Zones: H1 inner surface r = A, H2 outer surface r = B, H3..H7 pieces of the two end faces.
    """
    half = L_M / 2
    regions = [
        {
            "name": "lower",
            "material": "m",
            "heat": "front",
            "r0_m": A_M,
            "r1_m": B_M,
            "z0_m": 0.0,
            "z1_m": half,
        },
        {
            "name": "upper",
            "material": "m",
            "heat": "rear",
            "r0_m": A_M,
            "r1_m": B_M,
            "z0_m": half,
            "z1_m": L_M,
        },
    ]
    rm = 0.03
    zones = [
        _zone("H1", [[[A_M, 0.0], [A_M, L_M]]]),
        _zone("H2", [[[B_M, 0.0], [B_M, L_M]]]),
        _zone("H3", [[[A_M, 0.0], [rm, 0.0]]]),
        _zone("H4", [[[rm, 0.0], [B_M, 0.0]]]),
        _zone("H5", [[[A_M, L_M], [rm, L_M]]]),
        _zone("H6", [[[rm, L_M], [0.04, L_M]]]),
        _zone("H7", [[[0.04, L_M], [B_M, L_M]]]),
    ]
    sensors = []
    for i in range(32):
        r = A_M + (B_M - A_M) * (i + 0.5) / 32
        sensors.append(
            {"channel": i + 1, "name": f"s{i + 1}", "r_m": r, "z_m": 0.0371, "role": "housing"}
            | ({"test_point": i + 1} if i + 1 in (1, 3, 5, 7) else {})
        )
    bearing = {"f0": 1.0, "nu_mm2_s": 10.0, "dm_mm": 70.0, "f1": 0.0005, "p1_n": 500.0}
    return {
        "name": "cylinder",
        "materials": {"m": {"k_w_mk": k, "rho_kg_m3": rho, "c_j_kgk": c}},
        "regions": regions,
        "zones": zones,
        "sensors": sensors,
        "bearings": {"front": dict(bearing), "rear": dict(bearing)},
    }
