"""Loader: meshio round trips and every bad-file case raising a one-line InputError."""

from __future__ import annotations

import re
from pathlib import Path

import gmsh
import meshio
import numpy as np
import pytest
from support import EXTERNAL_MESHES

from meshes import MeshWarning, TetMesh, ValidationOptions, box, load, structured_box
from meshes.builders import gmsh_session
from meshes.errors import InputError


@pytest.fixture(scope="module")
def gmsh_box(tmp_path_factory: pytest.TempPathFactory) -> TetMesh:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("WRINKLES_CACHE", str(tmp_path_factory.mktemp("cache")))
        return box(1.0, 0.5, 0.4, 0.2)


def write(path: Path, points: np.ndarray, cells: list[tuple[str, np.ndarray]]) -> Path:
    # Once dolfinx is imported (by any earlier test) h5py runs on dolfinx's libhdf5, which has no
    # gzip filter; meshio's XDMF writer compresses with gzip by default, so turn that off.
    kwargs = {"compression": None} if path.suffix == ".xdmf" else {}
    meshio.write(path, meshio.Mesh(points, cells), **kwargs)
    return path


def load_error(path: Path, options: ValidationOptions | None = None) -> str:
    with pytest.raises(InputError) as info:
        load(path, options)
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    return message


@pytest.mark.parametrize("suffix", [".msh", ".vtu", ".xdmf", ".vtk", ".mesh"])
def test_round_trip_identical_arrays(gmsh_box, tmp_path: Path, suffix: str) -> None:
    path = write(tmp_path / f"body{suffix}", gmsh_box.points, [("tetra", gmsh_box.tets)])
    loaded = load(path)
    np.testing.assert_array_equal(loaded.points, gmsh_box.points)
    np.testing.assert_array_equal(loaded.tets, gmsh_box.tets)
    assert loaded.source == str(path)
    assert abs(loaded.volume - 0.2) <= 1e-12


def test_mixed_cells_unreferenced_points_and_tetra10(tmp_path: Path) -> None:
    m = structured_box((2, 1, 1))
    points = np.concatenate([m.points, [[9.0, 9.0, 9.0]]])
    cells = [("triangle", m.boundary), ("tetra", m.tets[:5]), ("tetra", m.tets[5:])]
    loaded = load(write(tmp_path / "mixed.vtu", points, cells))
    np.testing.assert_array_equal(loaded.points, m.points)
    np.testing.assert_array_equal(loaded.tets, m.tets)
    tet10 = np.concatenate([m.tets, np.zeros((m.n_tets, 6), dtype=np.int64) + 12], axis=1)
    from_quadratic = load(write(tmp_path / "quad.vtu", points, [("tetra10", tet10)]))
    np.testing.assert_array_equal(from_quadratic.tets, m.tets)


def test_inverted_tet_in_file(tmp_path: Path) -> None:
    m = structured_box((1, 1, 2))
    tets = m.tets.copy()
    tets[9, [2, 3]] = tets[9, [3, 2]]
    path = write(tmp_path / "inverted.vtu", m.points, [("tetra", tets)])
    with pytest.warns(MeshWarning, match=re.escape(f"{path}: re-oriented 1 inverted tets")):
        np.testing.assert_array_equal(load(path).tets, m.tets)
    message = load_error(path, ValidationOptions(fix_orientation=False))
    assert "tet 9 is inverted (volume -8.333e-02 < 0" in message
    with pytest.raises(InputError, match="tet 9 is inverted"):
        load(path, fix_orientation=False)


def test_degenerate_tet_in_file(tmp_path: Path) -> None:
    m = structured_box((1, 1, 1))
    points = m.points.copy()
    assert m.tets[0].tolist() == [0, 1, 3, 7]
    points[7] = [0.5, 0.5, 1e-12]  # tet 0 flat: det[(1,0,0), (1,1,0), (.5,.5,1e-12)] = 1e-12
    path = write(tmp_path / "degenerate.msh", points, [("tetra", m.tets)])
    assert "tet 0 is degenerate: volume 1.667e-13" in load_error(path)


def test_duplicate_tet_in_file(tmp_path: Path) -> None:
    m = structured_box((1, 1, 1))
    tets = np.concatenate([m.tets[:4], m.tets[3:4, [0, 2, 3, 1]], m.tets[4:]])
    message = load_error(write(tmp_path / "dup.xdmf", m.points, [("tetra", tets)]))
    assert "tets 3 and 4 are duplicates" in message


def test_dangling_tet_on_an_edge_in_file(tmp_path: Path) -> None:
    m = structured_box((1, 1, 1))
    extra = np.array([[2.0, 0.5, 0.0], [1.5, 0.5, -1.0]])  # tet on cube edge (1,0,0)-(1,1,0)
    points = np.concatenate([m.points, extra])
    tets = np.concatenate([m.tets, [[1, 3, 8, 9]]])
    assert np.linalg.det(points[[3, 8, 9]] - points[1]) > 0
    path = write(tmp_path / "dangling.vtu", points, [("tetra", tets)])
    message = load_error(path)
    assert "boundary edge [1, 3] is in 4 boundary triangles (tets [0, 6])" in message


def test_empty_mesh_file(tmp_path: Path) -> None:
    path = write(tmp_path / "empty.msh", np.zeros((0, 3)), [("tetra", np.zeros((0, 4), int))])
    assert load_error(path) == f"no tetrahedra in {path} (found: no cells, 0 points: empty mesh)"


def test_nan_coordinate_in_file(tmp_path: Path) -> None:
    m = structured_box((1, 1, 1))
    points = m.points.copy()
    points[6, 2] = np.nan
    message = load_error(write(tmp_path / "nan.vtu", points, [("tetra", m.tets)]))
    assert "point 6 (used by tet 3) has a non-finite coordinate" in message


def test_only_triangles(tmp_path: Path) -> None:
    m = structured_box((1, 1, 1))
    cells = [("triangle", m.boundary), ("line", m.boundary[:, :2])]
    path = write(tmp_path / "surface.vtu", m.points, cells)
    assert load_error(path) == f"no tetrahedra in {path} (found: line, triangle)"


def test_missing_and_unreadable_files(tmp_path: Path) -> None:
    missing = tmp_path / "nope.msh"
    assert load_error(missing) == f"{missing}: no such mesh file"
    garbage = tmp_path / "garbage.vtu"
    garbage.write_text("this is not a VTU file")
    assert load_error(garbage).startswith(f"{garbage}: cannot read mesh (")
    unknown = tmp_path / "body.unknownext"
    unknown.write_text("1 2 3")
    assert load_error(unknown).startswith(f"{unknown}: cannot read mesh (")


def test_msh_written_by_gmsh_with_lower_dimensional_cells(tmp_path: Path) -> None:
    path = tmp_path / "gmsh_box.msh"
    with gmsh_session("user-file"):
        gmsh.model.occ.addBox(0.0, 0.0, 0.0, 1.0, 2.0, 0.5)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.25)
        gmsh.model.mesh.generate(3)
        n_tets = gmsh.model.mesh.getElementsByType(4)[0].size
        gmsh.write(str(path))
    raw = meshio.read(path)
    assert {"vertex", "line", "triangle", "tetra"} <= {b.type for b in raw.cells}
    m = load(path)
    assert m.n_tets == n_tets and abs(m.volume - 1.0) <= 1e-12
    assert m.n_points == np.unique(m.tets).size


def test_load_overrides_and_vertex_pinch_in_file(tmp_path: Path) -> None:
    a = structured_box((1, 1, 1))
    b = structured_box((1, 1, 1), origin=(1.0, 1.0, 1.0))
    points = np.concatenate([a.points, b.points[1:]])  # b's corner 0 is a's corner 7
    tets = np.concatenate([a.tets, np.where(b.tets == 0, 7, b.tets + 7)])
    path = write(tmp_path / "pinch.vtu", points, [("tetra", tets)])
    assert "boundary vertex 7 joins 2 separate surface fans" in load_error(path)
    assert load(path, check_manifold=False).n_components == 2


def test_tets_with_hexahedra_refused_naming_types_and_counts(tmp_path: Path) -> None:
    """A tet + hex file is refused (the hexes were silently dropped before)."""
    tet = structured_box((1, 1, 1), (1.0, 1.0, 1.0))
    hexes = np.array([[0, 1, 3, 2, 4, 5, 7, 6]])
    path = write(tmp_path / "mixed.vtu", tet.points,
                 [("tetra", tet.tets), ("hexahedron", hexes)])
    with pytest.raises(InputError, match=r"mixed\.vtu: volume cells other than tetrahedra "
                                         r"\(1 hexahedron\)"):
        load(path)


EXTERNAL = EXTERNAL_MESHES


@pytest.mark.skipif(not EXTERNAL.is_dir(), reason="../shared/meshes_external not beside the repo")
@pytest.mark.parametrize(("name", "found"), [
    ("cinolib_rockerarm_hex.mesh", "10600 hexahedron"),
    ("polyfem_hybrid_block_mixed.msh", "16 pyramid, 8 wedge"),
])
def test_external_non_tet_meshes_refused(name: str, found: str) -> None:
    with pytest.raises(InputError, match=f"{re.escape(name)}: volume cells other than "
                                         f"tetrahedra \\({found}\\)"):
        load(EXTERNAL / name)


@pytest.mark.skipif(not EXTERNAL.is_dir(), reason="../shared/meshes_external not beside the repo")
@pytest.mark.parametrize(("name", "points", "tets"), [
    ("cinolib_sphere.mesh", 4505, 24013), ("ipc_bunny.msh", 4670, 19379),
    ("sfepy_elbow.mesh", 1823, 8161), ("sfepy_multi_material_cylinder_plate.vtk", 2101, 10440),
])
def test_external_tet_meshes_load(name: str, points: int, tets: int) -> None:
    mesh = load(EXTERNAL / name)
    assert mesh.points.shape == (points, 3) and mesh.tets.shape == (tets, 4)
