"""The served growth's mechanics: a commissioning's calibration and its posterior in ``/compensation`` (pure).

The service's ``[mechanics]`` (mount ``fix``, the materials' α) is a guess; a commissioning test
(``chtc commission growth``, docs/commissioning.md) fits the three parameters that matter
(``model.growthfit``): the mount's radial restraint s in [0, 1] (0 free, 1 held), and α factors of the
shaft's and the housing's material. Their posterior mean and covariance (3, 3) make the served operators::

    g(θ) = (1 − s) · (g_free,0 + a_s g_free,shaft + a_h g_free,housing) + s · (g_held,0 + ...)   (2, N)
    ∂g/∂θ (2, 3, N):  ∂/∂s = G_held − G_free,  ∂/∂a_s = (1 − s) g_free,shaft + s g_held,shaft,  ∂/∂a_h alike

for both served outputs (nose axial, nose radial), and the growth's mechanical 1σ at a field T over T_ref is
√(J Σ_θ Jᵀ) with J = ∂g/∂θ · (T − T_ref) (``service.estimate.growth``; exact to first order in θ: the
growth is bilinear in s and α). The fixture offset and the drift of the test set-up are the test's
nuisances: they are fitted and reported, never served.

Errors::

    MechanicsError(ValueError)   a calibration of the wrong shape or value, a basis for another mesh (named)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.fem import FEModel
from model.geometry import SpindleSpec
from model.mechprior import ALPHA_REL, alpha_region_scales
from model.thermoelastic import MechanicsVariant, build_growth_model

__all__ = [
    "PRIOR_MEAN",
    "PRIOR_SD",
    "ServedMechanicsBasis",
    "served_mechanics_basis",
]

Array = NDArray[np.float64]
SERVED = ("nose_axial", "nose_radial")
# what is known before a test: s anywhere in [0, 1] (uniform: mean 0.5, sd 1/√12 ≈ 0.29), α within ±5 %
# (uniform ±5 %: sd 0.05/√3 ≈ 0.029; the fit's Gaussian prior takes 0.05, wider)
PRIOR_MEAN = (0.5, 1.0, 1.0)
PRIOR_SD = (1.0 / math.sqrt(12.0), ALPHA_REL / math.sqrt(3.0), ALPHA_REL / math.sqrt(3.0))


@dataclass(frozen=True, eq=False)
class ServedMechanicsBasis:
    """``operators`` (2 outputs, 2 mounts (free, held), 3 groups (other, shaft's α, housing's α), N) [µm/K]
    for the served outputs (nose axial, nose radial): g_o,m(a_s, a_h) = op[o, m, 0] + a_s op[o, m, 1] + a_h
    op[o, m, 2]."""

    operators: Array

    @property
    def n_nodes(self) -> int:
        return int(self.operators.shape[3])

    def operators_at(self, x: ArrayLike) -> Array:
        """g(θ) (2, N) [µm/K] at θ = (s, a_s, a_h)."""
        s, a_s, a_h = (float(v) for v in np.asarray(x, dtype=float)[:3])
        op = self.operators
        g = op[:, :, 0] + a_s * op[:, :, 1] + a_h * op[:, :, 2]  # (2, 2, N)
        return np.asarray((1.0 - s) * g[:, 0] + s * g[:, 1])

    def jacobian_at(self, x: ArrayLike) -> Array:
        """∂g/∂θ (2, 3, N) [µm/K per unit θ] at θ = (s, a_s, a_h)."""
        s, a_s, a_h = (float(v) for v in np.asarray(x, dtype=float)[:3])
        op = self.operators
        g = op[:, :, 0] + a_s * op[:, :, 1] + a_h * op[:, :, 2]
        w = np.array([1.0 - s, s])
        return np.stack(
            [
                g[:, 1] - g[:, 0],
                np.einsum("omn,m->on", op[:, :, 1], w),
                np.einsum("omn,m->on", op[:, :, 2], w),
            ],
            axis=1,
        )


def served_mechanics_basis(spec: SpindleSpec, fe: FEModel) -> ServedMechanicsBasis:
    """The served outputs' operators on ``fe``'s mesh for both mount idealisations and the α groups (six
    growth-model builds: ~2 s at the service's mesh, once per process)."""
    base = np.array(alpha_region_scales(spec, 0.0, 0.0))
    shaft = np.array(alpha_region_scales(spec, 1.0, 0.0)) - base
    housing = np.array(alpha_region_scales(spec, 0.0, 1.0)) - base
    groups = [tuple(float(v) for v in g) for g in (base, shaft, housing)]
    ops = np.zeros((len(SERVED), 2, 3, fe.n_nodes))
    for m, fix in enumerate(("axial", "axial_radial")):
        for j, scales in enumerate(groups):
            gm = build_growth_model(spec, fe, variant=MechanicsVariant(fix=fix, region_alpha_scale=scales))
            for o, name in enumerate(SERVED):
                ops[o, m, j] = gm.operator(name)
    return ServedMechanicsBasis(operators=ops)
