"""The compensation reference: the spindle's temperature at which the served growth is 0 (pure, no I/O).

The controller's thermal compensation is zeroed once, at commissioning: the tool is measured and its offset
set while the spindle rests in equilibrium. The service must serve the growth *relative to that state*. The
reference is stored as one **uniform temperature** ``temperature_c`` [°C] with its 1σ ``sd_c`` [°C]:

- uniform, not the nodal field: it does not depend on the mesh or the reduced basis (a new model version keeps
  it), an operator can read and type it, and a zero is taken at rest in equilibrium, where the field *is*
  uniform;
- taken from the live state (``uniform_equivalent``): the uniform temperature whose axial growth equals the
  live field's, T_ref = g·T̂ / g·1. The growth served at that instant is then 0 exactly, and it is computed
  from the same filtered field the growth is served from later, so what both share (the filter's memory of
  the sensor noise, a common offset of the sensors) cancels instead of showing up as a growth at rest;
- at the first start (``equilibrium_zero``, only when configured: the premise is a spindle resting in
  equilibrium when the service first starts) the live field does not know the shaft's inside yet; under the
  premise it is the sensors' temperature, so the zero is the mean of the good, offset-corrected readings, 1σ
  their spread ÷ √n (noise and unknown offsets), refused while the spindle turns or the readings spread more
  than ``EQUILIBRIUM_SPREAD_C``;
- its 1σ is the filter's uncertainty of that growth at the instant (÷ g·1); the served growth carries it in
  its CI for as long as the reference is in use (``service.estimate.growth.estimate_growth``,
  ``t_ref_sd_c``). A temperature given by an operator has ``sd_c`` 0 (a declared fact).

``source`` says how it was set: "api" (``POST /compensation/reference``), "cli" (``chtc commission zero``),
"first_start" (``compensation.reference_on_first_start``: at the first converged live state of a service that
had none) or "config" (``compensation.reference_c``); ``set_by`` who (the name given with the request, or the
OS user); ``at`` when (UTC).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from service.contracts.reference import ReferenceError

__all__ = [
    "EQUILIBRIUM_SPREAD_C",
    "equilibrium_zero",
    "uniform_equivalent",
]

EQUILIBRIUM_SPREAD_C = 0.5  # 1σ [°C] across the good channels above which the spindle is not uniform
MIN_CHANNELS = 8  # good channels an equilibrium zero needs


def uniform_equivalent(
    g_row: ArrayLike, g1_um_per_k: float, state: ArrayLike, cov: ArrayLike
) -> tuple[float, float]:
    """(T_ref, 1σ) [°C]: the uniform temperature whose growth equals the field's, T_ref = g·a / g·1.

    ``g_row`` (r,) [µm/K] one growth functional on the reduced state (the axial row of ``g·Φ``),
    ``g1_um_per_k`` its growth per uniform kelvin (g·1), ``state`` (r,) [°C] and ``cov`` (r, r) [°C²] the
    live state's reduced mean and covariance. The 1σ is the growth's 1σ under ``cov`` divided by |g·1|.
    """
    g = np.asarray(g_row, dtype=float)
    a = np.asarray(state, dtype=float)
    p = np.asarray(cov, dtype=float)
    if not math.isfinite(g1_um_per_k) or abs(g1_um_per_k) < 1e-12:
        raise ReferenceError(
            f"g1_um_per_k: the growth per uniform kelvin must be non-zero, got {g1_um_per_k}"
        )
    if g.shape != a.shape or p.shape != (a.size, a.size):
        raise ReferenceError(
            f"state/cov: expected ({g.size},) and ({g.size}, {g.size}), got {a.shape}, {p.shape}"
        )
    t_ref = float(g @ a) / g1_um_per_k
    sd = math.sqrt(max(float(g @ p @ g), 0.0)) / abs(g1_um_per_k)
    return t_ref, sd


def equilibrium_zero(
    temps_c: ArrayLike, good: ArrayLike, offsets_c: ArrayLike | None, speed_rpm: float
) -> tuple[float, float] | None:
    """(T, 1σ) [°C] of a spindle resting in equilibrium from one sample: the mean of the good channels'
    readings (32,) [°C] minus their ``offsets_c`` (None: 0), 1σ their standard deviation ÷ √n; None while
    the spindle turns (``speed_rpm`` not 0), with fewer than ``MIN_CHANNELS`` good channels, or when the
    readings spread more than ``EQUILIBRIUM_SPREAD_C`` (not uniform)."""
    t = np.asarray(temps_c, dtype=float)
    off = np.zeros_like(t) if offsets_c is None else np.asarray(offsets_c, dtype=float)
    ok = np.asarray(good, dtype=bool) & np.isfinite(t) & np.isfinite(off)
    if not math.isfinite(speed_rpm) or speed_rpm != 0.0 or int(ok.sum()) < MIN_CHANNELS:
        return None
    x = t[ok] - off[ok]
    spread = float(np.std(x, ddof=1))
    if spread > EQUILIBRIUM_SPREAD_C:
        return None
    return float(np.mean(x)), spread / math.sqrt(x.size)
