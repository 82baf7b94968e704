"""Triangle mesh of a union of rectangles in the axisymmetric (r, z) plane, generated in pure numpy.

A tensor grid is laid through every rectangle edge; each interval between two edges is split into
ceil(length / size) equal cells, so the mesh is conforming at every material interface and boundary segment.
Cells not covered by any rectangle (air) are dropped; each kept quad is cut into two P1 triangles.

Errors::

    MeshError(ValueError)   no solid cells, or a bad mesh size
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from model.errors import ModelError
from model.geometry import Region


class MeshError(ModelError, ValueError):
    """The mesh cannot be built."""


@dataclass(frozen=True)
class RectMesh:
    """Nodes ``p`` (2, N) as (r, z) [m], triangles ``t`` (3, M), region index of each triangle (M,)."""

    p: NDArray[np.float64]
    t: NDArray[np.int64]
    region: NDArray[np.int64]


def graded_axis(breaks: Sequence[float], size_m: float) -> NDArray[np.float64]:
    """Coordinates [m] through all ``breaks``, each interval split into ceil(len/size) equal parts."""
    b = np.unique(np.round(np.asarray(breaks, dtype=float), 12))
    pieces = [b[:1]]
    for a, c in itertools.pairwise(b):
        n = max(1, int(np.ceil((c - a) / size_m - 1e-9)))
        pieces.append(np.linspace(a, c, n + 1)[1:])
    return np.concatenate(pieces)


def _cell_regions(
    rs: NDArray[np.float64], zs: NDArray[np.float64], regions: Sequence[Region]
) -> NDArray[np.int64]:
    rc = 0.5 * (rs[:-1] + rs[1:])
    zc = 0.5 * (zs[:-1] + zs[1:])
    owner = np.full((len(rc), len(zc)), -1, dtype=np.int64)
    for idx in range(len(regions) - 1, -1, -1):  # first region in file order wins
        g = regions[idx]
        inr = (rc > g.r0_m) & (rc < g.r1_m)
        inz = (zc > g.z0_m) & (zc < g.z1_m)
        owner[np.ix_(inr, inz)] = idx
    return owner


def _with_points(breaks: list[float], extra: Sequence[float], min_gap_m: float) -> list[float]:
    """Add ``extra`` coordinates to ``breaks`` unless closer than ``min_gap_m`` to one already there."""
    out = list(breaks)
    for x in sorted(extra):
        if min(abs(x - b) for b in out) >= min_gap_m:
            out.append(x)
    return out


def rect_mesh(
    regions: Sequence[Region],
    size_m: float,
    *,
    points_rz: Sequence[tuple[float, float]] = (),
    edges_rz: Sequence[tuple[float, float]] = (),
) -> RectMesh:
    """Mesh the union of ``regions`` with target edge length ``size_m`` [m].

    Grid lines are also drawn through ``points_rz`` (e.g. sensors) unless that would create a cell thinner
    than 0.4 size_m; a point on two grid lines is a mesh node, which removes its interpolation error.
    ``edges_rz`` (e.g. zone segment ends) always get grid lines, so boundary tags fall on facet ends.
    """
    if not size_m > 0:
        raise MeshError(f"mesh size_m: must be > 0, got {size_m!r}")
    gap = 0.4 * size_m
    rb = [v for g in regions for v in (g.r0_m, g.r1_m)] + [e[0] for e in edges_rz]
    zb = [v for g in regions for v in (g.z0_m, g.z1_m)] + [e[1] for e in edges_rz]
    rb = _with_points(rb, [p[0] for p in points_rz], gap)
    zb = _with_points(zb, [p[1] for p in points_rz], gap)
    rs = graded_axis(rb, size_m)
    zs = graded_axis(zb, size_m)
    owner = _cell_regions(rs, zs, regions)
    ii, jj = np.nonzero(owner >= 0)
    if ii.size == 0:
        raise MeshError("regions: no solid cells")
    nz = len(zs)
    n00 = ii * nz + jj
    n10 = (ii + 1) * nz + jj
    n01 = ii * nz + jj + 1
    n11 = (ii + 1) * nz + jj + 1
    tri = np.concatenate([np.stack([n00, n10, n11]), np.stack([n00, n11, n01])], axis=1)
    reg = np.concatenate([owner[ii, jj], owner[ii, jj]])
    used, inverse = np.unique(tri, return_inverse=True)
    t = inverse.reshape(tri.shape).astype(np.int64)
    R, Z = np.meshgrid(rs, zs, indexing="ij")
    p = np.stack([R.ravel()[used], Z.ravel()[used]])
    return RectMesh(p=p, t=t, region=reg.astype(np.int64))
