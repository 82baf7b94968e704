"""The served thermal growth (``GrowthEstimate`` with its ``GrowthValue``s and forecast) and the controller
values of one growth (``PlcCompensation``): computed by ``service.estimate.growth``, served by
``/compensation``, OPC UA and MQTT (docs/design/growth.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

import numpy as np

__all__ = ["GrowthEstimate", "GrowthForecastEstimate", "GrowthValue", "PlcCompensation"]


@dataclass(frozen=True, kw_only=True)
class GrowthValue:
    """One growth [µm] with its 1σ parts (field, H, mechanics), total 1σ, 95 % CIs (total and each part
    alone) and the value in 0.1 µm as an integer for a PLC."""

    um: float
    std_field_um: float
    std_h_um: float
    std_um: float
    ci95_um: tuple[float, float]
    ci95_field_um: tuple[float, float]
    ci95_h_um: tuple[float, float]
    plc_0p1um: int
    std_mech_um: float = 0.0
    ci95_mech_um: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def of(cls, um: float, std_field_um: float, std_h_um: float, std_mech_um: float = 0.0) -> GrowthValue:
        """The value with the parts combined as independent."""
        from model.growth import Z95  # here: the model's numerics stay out of the types' import

        total = float(np.sqrt(std_field_um**2 + std_h_um**2 + std_mech_um**2))

        def ci(s: float) -> tuple[float, float]:
            return (float(um - Z95 * s), float(um + Z95 * s))

        return cls(
            um=float(um),
            std_field_um=float(std_field_um),
            std_h_um=float(std_h_um),
            std_um=total,
            ci95_um=ci(total),
            ci95_field_um=ci(std_field_um),
            ci95_h_um=ci(std_h_um),
            plc_0p1um=int(np.rint(10.0 * um)),
            std_mech_um=float(std_mech_um),
            ci95_mech_um=ci(std_mech_um),
        )


@dataclass(frozen=True, kw_only=True)
class GrowthForecastEstimate:
    """If the condition and H hold: the steady growth, the dominant time constant of the axial growth's
    remaining change ``tau_s`` [s] (and the thermal model's slowest), and the growth at ``horizons_s``."""

    steady_axial: GrowthValue
    steady_radial: GrowthValue
    tau_s: float
    slowest_tau_s: float
    horizons_s: tuple[float, ...]
    axial: tuple[GrowthValue, ...]
    radial: tuple[GrowthValue, ...]


@dataclass(frozen=True, kw_only=True)
class GrowthEstimate:
    """The growth at the spindle nose [µm] relative to the mounting face at ``at`` (UTC), over the reference
    temperature ``t_ref_c`` (uniform; the state at which the controller was zeroed); axial + towards the
    tool. ``sensitivity_*`` (32,) [µm/°C]: growth per unit temperature error of each sensor channel."""

    at: datetime
    t_ref_c: float
    axial: GrowthValue
    radial: GrowthValue
    forecast: GrowthForecastEstimate
    sensitivity_axial_um_per_k: tuple[float, ...]
    sensitivity_radial_um_per_k: tuple[float, ...]
    h: tuple[float, ...]
    ambient_c: float


@dataclass(frozen=True, kw_only=True)
class PlcCompensation:
    """Values a PLC writes to a CNC for one growth [µm] (docs/design/growth.md, "Controller mapping").

    ``correction_um``: the axis correction that cancels the nose's axial growth, −tool_dir·growth: the tool
    tip moved by tool_dir·growth along the machine axis, so the axis must move the other way.

    Siemens SINUMERIK (position-independent temperature compensation, MD32750 bit 0): SD43900
    ``$SA_TEMP_COMP_ABS_VALUE`` [mm] = the correction; SD43910 ``TEMP_COMP_SLOPE`` = 0 and SD43920
    ``TEMP_COMP_REF_POSITION`` = 0 (the spindle's growth does not depend on the axis position). Or, in tool
    direction (MD20390 ``$MC_TOOL_TEMP_COMP_ON``, MD32750 bit 2): the growth as a tool-length increase
    [mm], the SD42960 ``$SC_TOOL_TEMP_COMP`` component that acts along the spindle axis.

    Beckhoff TwinCAT CNC / ISG (Δs = offset0 + coefficient·(s − s0)): P-AXIS-00273 ``temp_comp_offset_0``
    [0.1 µm, SGN32] = the correction; P-AXIS-00274 ``temp_comp_coefficient`` [µm/m] = 0 and P-AXIS-00272
    ``temp_comp_position_0`` [0.1 µm] = 0.
    """

    growth_um: float
    correction_um: float
    sd43900_mm: float
    sd43910_slope: float
    sd43920_ref_mm: float
    sd42960_tool_axis_mm: float
    isg_offset_0p1um: int
    isg_coefficient_um_per_m: float
    isg_position_0p1um: int
