"""The 1-D axial approximation of the growth: ∫ α ΔT dz along the load path (pure).

The load path from the mounting face to the tool reference point: back through the housing wall from the
mount (z_mount) to the locating plane (z_loc) of the front bearing pair, then forward along the shaft to the
nose (z_nose)::

    δ_nose ≈ −∫_{z_loc}^{z_mount} α_h ΔT_h(z) dz + ∫_{z_loc}^{z_nose} α_s ΔT_s(z) dz

ΔT_h, ΔT_s are the temperature rises of the housing wall and the shaft at z, averaged over the section
(area weight 2πr) or taken on one line; α is the material's at each sampled point. This is what a
compensation built on a few temperatures and linear rules assumes; ``benchmarks.studies.growth_check`` sets it
beside the 2-D result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import trapezoid
from skfem import Basis, ElementTriP1, MeshTri

from model.fem import FEModel
from model.geometry import SpindleSpec

Array = NDArray[np.float64]
_INSET = 1e-7  # sample points kept this far inside the band [m] so that they fall in the mesh


@dataclass(frozen=True)
class Band:
    """A path segment: radii r0..r1 (r0 == r1: one line) and z0..z1 [m]."""

    r0_m: float
    r1_m: float
    z0_m: float
    z1_m: float


def _alpha(spec: SpindleSpec, r: Array, z: Array) -> Array:
    override = spec.mechanics.region_material if spec.mechanics is not None else {}
    out = np.full(r.shape, np.nan)
    for g in reversed(spec.regions):  # first region in file order wins, as in the mesh
        a = spec.materials[override.get(g.name, g.material)].alpha_per_k
        inside = (r >= g.r0_m - 1e-12) & (r <= g.r1_m + 1e-12) & (z >= g.z0_m - 1e-12) & (z <= g.z1_m + 1e-12)
        out[inside] = np.nan if a is None else a
    return out


def band_integral_m(
    spec: SpindleSpec, fe: FEModel, rise_c: ArrayLike, band: Band, *, n_r: int = 12, n_z: int = 200
) -> float:
    """∫_{z0}^{z1} ⟨α ΔT⟩(z) dz [m]; ⟨·⟩ is the 2πr-weighted mean over r0..r1 (or the value on r0 = r1)."""
    rs = np.linspace(band.r0_m + _INSET, band.r1_m - _INSET, n_r) if band.r1_m > band.r0_m else [band.r0_m]
    rs = np.maximum(np.asarray(rs, dtype=float), _INSET)
    zs = np.linspace(band.z0_m, band.z1_m, n_z)  # integration nodes; sampled just inside the band's ends
    R, Z = np.meshgrid(rs, np.clip(zs, band.z0_m + _INSET, band.z1_m - _INSET), indexing="ij")
    mesh = MeshTri(np.ascontiguousarray(fe.nodes_rz.T), np.ascontiguousarray(fe.triangles.T))
    basis = Basis(mesh, ElementTriP1())
    probe = basis.probes(np.vstack([R.ravel(), Z.ravel()]))
    val = (_alpha(spec, R.ravel(), Z.ravel()) * (probe @ np.asarray(rise_c, dtype=float))).reshape(R.shape)
    if np.isnan(val).any():
        raise ValueError(f"band: part of {band} is not in a solid with alpha_per_k")
    mean = np.average(val, axis=0, weights=R[:, 0]) if rs.size > 1 else val[0]
    return float(trapezoid(mean, zs))


def axial_1d_um(
    spec: SpindleSpec,
    fe: FEModel,
    rise_c: ArrayLike,
    *,
    housing: Band,
    shaft: Band,
) -> float:
    """Nose growth [µm] by the 1-D rule: −∫ housing band (locating plane to mount) + ∫ shaft band."""
    return 1e6 * (band_integral_m(spec, fe, rise_c, shaft) - band_integral_m(spec, fe, rise_c, housing))
