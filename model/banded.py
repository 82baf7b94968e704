"""Banded Cholesky solver for the symmetric positive definite FE systems.

The spindle is long and thin, so numbering the nodes along the long axis (then across) gives a narrow band
(about the number of nodes across the section); LAPACK's banded Cholesky (dpbtrf/dpbtrs) then solves
1.5-3x faster per step than a general sparse LU on this geometry.

Errors::

    SolverError(ValueError)   the matrix is not positive definite (e.g. all H = 0 in a steady solve)
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg.lapack import dpbtrf, dpbtrs

from model.errors import ModelError


class SolverError(ModelError, ValueError):
    """The system cannot be factorised."""


def band_order(nodes_rz: NDArray[np.float64]) -> NDArray[np.int64]:
    """Node permutation along the axis with more distinct coordinates (then the other one)."""
    r, z = nodes_rz[:, 0], nodes_rz[:, 1]
    if np.unique(np.round(z, 12)).size >= np.unique(np.round(r, 12)).size:
        return np.lexsort((r, z)).astype(np.int64)
    return np.lexsort((z, r)).astype(np.int64)


class BandedCholesky:
    """Cholesky factor of a sparse SPD matrix A in the node order ``perm``; ``solve(b)`` returns A^-1 b."""

    def __init__(self, A: sp.spmatrix, perm: NDArray[np.int64]) -> None:
        Ap = sp.csr_matrix(A)[perm][:, perm].tocoo()
        upper = Ap.row <= Ap.col
        bw = int(np.max(Ap.col[upper] - Ap.row[upper]))
        ab = np.zeros((bw + 1, Ap.shape[0]), order="F")
        ab[bw + Ap.row[upper] - Ap.col[upper], Ap.col[upper]] = Ap.data[upper]
        factor, info = dpbtrf(ab, lower=0, overwrite_ab=1)
        if info != 0:
            raise SolverError(f"matrix is not positive definite (LAPACK dpbtrf info={info})")
        self.factor, self.perm, self.bandwidth = factor, perm, bw

    def solve(self, b: NDArray[np.float64]) -> NDArray[np.float64]:
        """x with A x = b, for b of shape (N,)."""
        y, _info = dpbtrs(self.factor, b[self.perm], lower=0)
        out = np.empty_like(y)
        out[self.perm] = y
        return out
