"""Boundary surface extraction: counts, outward orientation, determinism, dolfinx gathering."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError
from meshes.structured import structured_box
from models.backend import MPI, dolfinx
from models.embedding.embedding import mesh_surface
from models.embedding.subdivision import edge_topology
from models.embedding.surface import boundary_surface, canonical_faces, signed_volume

SHAPE, SIZE = (2, 3, 4), (1.0, 1.5, 2.5)


def face_normals(s):
    v, f = s.vertices, s.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def expected_outward_normal(centroids, size):
    """Axis normal of the box side each face centroid lies on."""
    lo = np.isclose(centroids, 0.0, atol=1e-12)
    hi = np.isclose(centroids, np.asarray(size), atol=1e-12)
    return hi.astype(float) - lo.astype(float)


def test_box_surface_counts_orientation_and_volume(rng):
    m = structured_box(SHAPE, size=SIZE)
    tets = m.tets.copy()
    flip = rng.random(tets.shape[0]) < 0.5  # negatively oriented cells, as dolfinx may give
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    s = boundary_surface(m.points, tets)
    nx, ny, nz = SHAPE
    assert s.faces.shape[0] == 4 * (nx * ny + ny * nz + nz * nx)
    assert s.vertices.shape[0] == (nx + 1) * (ny + 1) * (nz + 1) - (nx - 1) * (ny - 1) * (nz - 1)
    assert signed_volume(s.vertices, s.faces) == pytest.approx(np.prod(SIZE), rel=1e-14)
    centroids = s.vertices[s.faces].mean(axis=1)
    np.testing.assert_allclose(face_normals(s), expected_outward_normal(centroids, SIZE),
                               atol=1e-14)
    np.testing.assert_array_equal(m.points[s.node_map], s.vertices)
    assert np.all(edge_topology(s.faces, s.vertices.shape[0]).edge_faces == 2)


def test_surface_independent_of_tet_order(rng):
    m = structured_box(SHAPE, size=SIZE)
    ref = boundary_surface(m.points, m.tets)
    tets = m.tets[rng.permutation(m.tets.shape[0])]
    tets = np.take_along_axis(tets, np.argsort(rng.random(tets.shape), axis=1), axis=1)
    other = boundary_surface(m.points, tets)
    np.testing.assert_array_equal(ref.faces, other.faces)
    np.testing.assert_array_equal(ref.node_map, other.node_map)


def test_canonical_faces_keeps_orientation():
    f = np.array([[5, 2, 7], [1, 9, 3]])
    np.testing.assert_array_equal(canonical_faces(f), [[1, 9, 3], [2, 7, 5]])


def test_degenerate_boundary_tet_raises():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    with pytest.raises(InputError, match="element 0 is degenerate"):
        boundary_surface(p, np.array([[0, 1, 2, 3]]))


def test_dolfinx_mesh_surface_matches_numpy_extraction():
    mesh = dolfinx.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], list(SIZE)], list(SHAPE),
                                   dolfinx.mesh.CellType.tetrahedron)
    s = mesh_surface(mesh)
    assert signed_volume(s.vertices, s.faces) == pytest.approx(np.prod(SIZE), rel=1e-14)
    igi = mesh.geometry.input_global_indices
    points = np.empty((igi.size, 3))
    points[igi] = mesh.geometry.x
    tets = igi[mesh.geometry.dofmaps[0]]
    ref = boundary_surface(points, tets)
    np.testing.assert_array_equal(s.faces, ref.faces)
    np.testing.assert_array_equal(s.node_map, ref.node_map)
    np.testing.assert_array_equal(s.vertices, ref.vertices)
