"""Mesh generation details and the mesh study helper."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies.fe_check import mesh_study
from model.geometry import Region
from model.mesh import MeshError, graded_axis, rect_mesh


def test_graded_axis_hits_every_break_with_cells_no_longer_than_size() -> None:
    x = graded_axis([0.0, 0.1, 0.013, 0.05], 0.01)
    assert {0.0, 0.013, 0.05, 0.1} <= set(np.round(x, 12))
    assert np.all(np.diff(x) > 0) and np.diff(x).max() <= 0.01 + 1e-12


def test_rect_mesh_is_conforming_and_drops_air() -> None:
    regions = [Region("a", "m", 0.0, 0.02, 0.0, 0.05), Region("b", "m", 0.02, 0.03, 0.02, 0.03)]
    m = rect_mesh(regions, 0.004, points_rz=[(0.011, 0.0251)])
    r, z = m.p
    centroid_r, centroid_z = r[m.t].mean(axis=0), z[m.t].mean(axis=0)
    in_a = (centroid_r < 0.02) & (centroid_z < 0.05)
    in_b = (centroid_r > 0.02) & (centroid_z > 0.02) & (centroid_z < 0.03)
    assert np.all(in_a | in_b) and np.all(m.region[in_b] == 1)
    x1, x2, x3 = (m.p[:, m.t[i]] for i in range(3))
    area = 0.5 * np.abs((x2[0] - x1[0]) * (x3[1] - x1[1]) - (x3[0] - x1[0]) * (x2[1] - x1[1]))
    assert area.sum() == pytest.approx(0.02 * 0.05 + 0.01 * 0.01, rel=1e-12)
    assert np.any(np.isclose(r, 0.011) & np.isclose(z, 0.0251))  # the point became a node
    with pytest.raises(MeshError, match=r"^mesh size_m"):
        rect_mesh(regions, 0.0)


def test_mesh_study_error_shrinks_with_the_mesh(spec) -> None:  # type: ignore[no-untyped-def]
    rows = mesh_study(spec, [0.012, 0.008], ref_size_m=0.005, repeats=1)
    assert rows[0].n_nodes < rows[1].n_nodes
    assert rows[0].max_err_c > rows[1].max_err_c > 0
    assert rows[1].max_rise_c > 5.0
