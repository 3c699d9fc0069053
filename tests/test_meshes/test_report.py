"""What the mesh report tells a user about an accepted mesh (meshes/report.py)."""

from __future__ import annotations

import warnings

import meshio
import numpy as np
import pytest
from support import EXTERNAL_MESHES

from meshes import MeshWarning, load, structured_box
from meshes.report import coincident_points, components, mesh_report, tet_quality
from meshes.tetmesh import TetMesh


def test_quality_is_one_for_a_regular_tet_and_small_for_a_sliver():
    regular = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    sliver = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 0.5, 1e-3]])
    q = tet_quality(np.vstack([regular, sliver]), np.array([[0, 1, 2, 3], [4, 5, 6, 7]]))
    assert q[0] == pytest.approx(1.0, rel=1e-12)
    assert 0 < q[1] < 1e-2


def test_two_boxes_are_two_components_and_a_crack_is_reported():
    box = structured_box((2, 2, 2))
    shifted = TetMesh(box.points + [3.0, 0.0, 0.0], box.tets)
    two = TetMesh(np.vstack([box.points, shifted.points]),
                  np.vstack([box.tets, box.tets + box.n_points]))
    assert components(two.n_points, two.tets) == 2
    cracked = TetMesh(np.vstack([box.points, box.points]),
                      np.vstack([box.tets[:8], box.tets[8:] + box.n_points]))
    report = mesh_report(cracked)
    assert report.coincident_points > 0 and coincident_points(box.points) == 0
    messages = report.warnings("cracked.vtu")
    assert any("points coincide" in m for m in messages)
    assert mesh_report(box).warnings("box") == []


def test_cell_data_of_a_file_is_reported_as_ignored(tmp_path):
    box = structured_box((2, 1, 1))
    path = tmp_path / "regions.vtu"
    ids = np.arange(box.n_tets) % 2 + 1
    meshio.write(path, meshio.Mesh(box.points, [("tetra", box.tets)],
                                   cell_data={"mat_id": [ids]}))
    with pytest.warns(MeshWarning, match=r"regions\.vtu: cell data ignored.*mat_id \(2 values: "
                                         r"1, 2\)"):
        load(path)


@pytest.mark.skipif(not EXTERNAL_MESHES.is_dir(), reason="../shared/meshes_external missing")
def test_external_meshes_report_their_slivers_and_material_ids():
    report = mesh_report(load(EXTERNAL_MESHES / "ipc_bunny.msh"))
    assert report.components == 1 and report.low_quality == 212  # as meshstats.py counts
    assert report.min_quality == pytest.approx(0.0042, abs=1e-4)
    with pytest.warns(MeshWarning, match=r"mat_id \(4 values: 1, 2, 3, 4\)"):
        load(EXTERNAL_MESHES / "sfepy_multi_material_cylinder_plate.vtk")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert mesh_report(load(EXTERNAL_MESHES / "sfepy_elbow.mesh")).warnings("elbow") == []
