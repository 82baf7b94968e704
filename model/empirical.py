"""Empirical convective heat transfer coefficients (the paper's baseline, eqs. 1-4, plus natural convection).

Rotating zones (forced convection over the rotating surface)::

    v = 2 pi r n / 60,  Re = v d / nu
    Nu = 0.664 Re^(1/2) Pr^(1/3)       Re <  5e5 (laminar)
    Nu = 0.037 Re^(4/5) Pr^(1/3)       Re >= 5e5 (turbulent; the paper prints 1/2, 4/5 is the standard form)
    H  = Nu lambda / l

Stationary zones: Churchill-Chu natural convection of a horizontal cylinder of diameter D::

    Ra = g beta dT D^3 / (nu alpha),   Nu = (0.60 + 0.387 Ra^(1/6) / (1 + (0.559/Pr)^(9/16))^(8/27))^2

Rotating zones never fall below that natural-convection value (at standstill Re = 0). Air properties are taken
at the film temperature Ti + dT/2, with an assumed surface rise dT (default 10 K). r, d, l and D come from the
zone entries of the spindle TOML (radius_m, diameter_m, length_m). Radiation is not included.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from model.geometry import SpindleSpec, ZoneSpec

G_M_S2 = 9.81
P_AIR_PA = 101325.0
R_AIR_J_KGK = 287.05
RE_CRITICAL = 5e5


@dataclass(frozen=True)
class AirProperties:
    """Dry air: conductivity [W/(m K)], kinematic viscosity [m^2/s], Prandtl [-], expansion beta [1/K]."""

    k_w_mk: float
    nu_m2_s: float
    pr: float
    beta_1_k: float


def air_properties(temp_c: float) -> AirProperties:
    """Air at temp_c [degC], 1 atm: Sutherland viscosity, ideal-gas density, power-law conductivity."""
    t = temp_c + 273.15
    mu = 1.716e-5 * (t / 273.15) ** 1.5 * (273.15 + 110.4) / (t + 110.4)
    rho = P_AIR_PA / (R_AIR_J_KGK * t)
    k = 0.0241 * (t / 273.15) ** 0.81
    return AirProperties(k_w_mk=k, nu_m2_s=mu / rho, pr=0.71, beta_1_k=1.0 / t)


def forced_nusselt(re: float, pr: float) -> float:
    """Flat-plate Nusselt number: laminar 0.664 Re^0.5 Pr^(1/3), turbulent 0.037 Re^0.8 Pr^(1/3)."""
    if re < RE_CRITICAL:
        return 0.664 * re**0.5 * pr ** (1 / 3)
    return 0.037 * re**0.8 * pr ** (1 / 3)


def churchill_chu_nusselt(ra: float, pr: float) -> float:
    """Churchill-Chu mean Nusselt number of a horizontal cylinder (valid Ra <= 1e12)."""
    return (0.60 + 0.387 * ra ** (1 / 6) / (1 + (0.559 / pr) ** (9 / 16)) ** (8 / 27)) ** 2


def natural_h(zone: ZoneSpec, air: AirProperties, surface_rise_k: float) -> float:
    """Natural-convection H [W/(m^2 K)] of a horizontal cylinder of diameter zone.diameter_m."""
    d = zone.diameter_m
    ra = G_M_S2 * air.beta_1_k * max(surface_rise_k, 0.0) * d**3 * air.pr / air.nu_m2_s**2
    return churchill_chu_nusselt(ra, air.pr) * air.k_w_mk / d


def rotating_h(zone: ZoneSpec, air: AirProperties, speed_rpm: float) -> float:
    """Forced-convection H [W/(m^2 K)] of a rotating zone at speed [rpm]."""
    v = 2 * np.pi * zone.radius_m * abs(speed_rpm) / 60.0
    re = v * zone.diameter_m / air.nu_m2_s
    return forced_nusselt(re, air.pr) * air.k_w_mk / zone.length_m


def empirical_h(
    spec: SpindleSpec, speed_rpm: float, ambient_c: float, *, surface_rise_k: float = 10.0
) -> NDArray[np.float64]:
    """Empirical H1..H7 [W/(m^2 K)] at speed [rpm] and ambient [degC] (not clipped to the search box)."""
    air = air_properties(ambient_c + 0.5 * surface_rise_k)
    out = []
    for zone in spec.zones:
        h = natural_h(zone, air, surface_rise_k)
        if zone.rotating:
            h = max(h, rotating_h(zone, air, speed_rpm))
        out.append(h)
    return np.array(out)
