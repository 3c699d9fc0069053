"""The embedding matrix B (P1 and P2): partition of unity, polynomial reproduction, fallback."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError
from models.backend import MPI, dolfinx
from models.embedding.embedding import (
    EmbeddingOptions,
    add_transpose_to_function,
    apply_to_function,
    build_embedding,
    mesh_surface,
)
from models.embedding.subdivision import SubdivisionOptions, subdivide

COMM = MPI.COMM_SELF
SIZE = (1.0, 1.5, 1.2)


def box_mesh():
    return dolfinx.mesh.create_box(COMM, [[0.0, 0.0, 0.0], list(SIZE)], [2, 3, 2],
                                   dolfinx.mesh.CellType.tetrahedron)


def l_shaped_mesh():
    """[0,2]x[0,2]x[0,1] without the quadrant x > 1, y > 1: concave edge along x = y = 1."""
    box = dolfinx.mesh.create_box(COMM, [[0.0, 0.0, 0.0], [2.0, 2.0, 1.0]], [4, 4, 2],
                                  dolfinx.mesh.CellType.tetrahedron)
    cells = dolfinx.mesh.locate_entities(box, 3, lambda x: ~((x[0] > 1.0) & (x[1] > 1.0)))
    return dolfinx.mesh.create_submesh(box, 3, cells)[0]


def vector_space(mesh, degree):
    return dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (3,)))


def linear_field(x):
    return np.stack([1.0 + 2.0 * x[0] - x[1], 0.5 * x[2] - 3.0, x[0] + x[1] + x[2]])


def quadratic_field(x):
    return np.stack([x[0] * x[1] - x[2] ** 2, 1.0 + x[1] ** 2, x[0] * x[2] + x[1]])


def shell_points(mesh, scheme, levels=2):
    s = mesh_surface(mesh)
    return subdivide(s.vertices, s.faces, SubdivisionOptions(levels=levels, scheme=scheme))


def interior_points(rng, n=200):
    return rng.random((n, 3)) * np.asarray(SIZE)


@pytest.mark.parametrize("degree", [1, 2])
@pytest.mark.parametrize("scheme", ["linear", "loop"])
def test_rows_sum_to_one_and_rest_shell(degree, scheme):
    V = vector_space(box_mesh(), degree)
    sub = shell_points(V.mesh, scheme)
    emb = build_embedding(V, sub.vertices)
    B = emb.global_matrix()
    assert B.shape == (sub.vertices.shape[0], V.dofmap.index_map.size_global)
    assert np.abs(np.asarray(B.sum(axis=1)).ravel() - 1.0).max() < 1e-13
    rest = B @ V.tabulate_dof_coordinates()
    assert np.abs(rest - sub.vertices).max() < 1e-13
    assert emb.report.n_inside == sub.vertices.shape[0]  # a convex box: Loop stays inside


@pytest.mark.parametrize("degree,field", [(1, linear_field), (2, linear_field),
                                          (2, quadratic_field)])
def test_polynomial_fields_reproduced(degree, field, rng):
    V = vector_space(box_mesh(), degree)
    u = dolfinx.fem.Function(V)
    u.interpolate(field)
    pts = np.vstack([shell_points(V.mesh, "loop").vertices, interior_points(rng)])
    emb = build_embedding(V, pts)
    err = np.abs(apply_to_function(emb, u) - field(pts.T).T).max()
    assert err < 1e-12, err
    if degree == 1:  # a quadratic field is not reproduced by P1: the test can fail
        w = dolfinx.fem.Function(V)
        w.interpolate(quadratic_field)
        assert np.abs(apply_to_function(emb, w) - quadratic_field(pts.T).T).max() > 1e-2


def test_p2_dof_points_give_identity_rows():
    V = vector_space(box_mesh(), 2)
    emb = build_embedding(V, V.tabulate_dof_coordinates())
    B = emb.global_matrix().toarray()
    np.testing.assert_allclose(B, np.eye(B.shape[0]), atol=1e-13)


def test_p1_linear_subdivision_is_prolongation_of_surface_rows():
    V = vector_space(box_mesh(), 1)
    s = mesh_surface(V.mesh)
    sub = subdivide(s.vertices, s.faces, SubdivisionOptions(levels=2))
    coarse = build_embedding(V, s.vertices).global_matrix()
    dense = coarse.toarray()  # surface nodes are P1 dofs: one weight 1 per row
    assert np.abs(dense - np.round(dense)).max() < 1e-13
    assert np.array_equal(np.round(dense).sum(axis=1), np.ones(dense.shape[0]))
    assert np.array_equal(np.round(dense).max(axis=1), np.ones(dense.shape[0]))
    fine = build_embedding(V, sub.vertices).global_matrix()
    assert abs(fine - sub.prolongation @ coarse).max() < 1e-14


@pytest.mark.parametrize("degree", [1, 2])
def test_loop_on_concave_body_uses_fallback(degree):
    V = vector_space(l_shaped_mesh(), degree)
    sub = shell_points(V.mesh, "loop")
    emb = build_embedding(V, sub.vertices)
    assert emb.report.n_extrapolated > 0
    assert 0.0 < emb.report.max_distance <= 0.25 * np.sqrt(3 * 0.5**2)
    B = emb.global_matrix()
    assert np.abs(np.asarray(B.sum(axis=1)).ravel() - 1.0).max() < 1e-13
    assert np.abs(B @ V.tabulate_dof_coordinates() - sub.vertices).max() < 1e-12
    u = dolfinx.fem.Function(V)
    u.interpolate(quadratic_field if degree == 2 else linear_field)
    exact = (quadratic_field if degree == 2 else linear_field)(sub.vertices.T).T
    assert np.abs(apply_to_function(emb, u) - exact).max() < 1e-12
    with pytest.raises(InputError, match="outside the coarse mesh"):
        build_embedding(V, sub.vertices,
                        EmbeddingOptions(max_distance=0.5 * emb.report.max_distance))


def test_point_outside_tolerance_names_it():
    V = vector_space(box_mesh(), 1)
    pts = shell_points(V.mesh, "linear", levels=1).vertices.copy()
    pts[7] = [SIZE[0] + 0.3, 0.5, 0.5]
    with pytest.raises(InputError, match=r"shell point 7 .* by 0\.3 "):
        build_embedding(V, pts, EmbeddingOptions(max_distance=0.1))
    emb = build_embedding(V, pts, EmbeddingOptions(max_distance=0.31))
    assert emb.report.n_extrapolated == 1
    assert emb.report.max_distance == pytest.approx(0.3, rel=1e-12)


def test_transpose_is_adjoint(rng):
    V = vector_space(box_mesh(), 2)
    emb = build_embedding(V, shell_points(V.mesh, "loop").vertices)
    u = dolfinx.fem.Function(V)
    u.interpolate(quadratic_field)
    forces = rng.standard_normal((emb.local.shape[0], 3))
    f = dolfinx.fem.Function(V)
    add_transpose_to_function(emb, forces, f)
    lhs = float(np.sum(f.x.array * u.x.array))
    rhs = float(np.sum(forces * apply_to_function(emb, u)))
    assert lhs == pytest.approx(rhs, rel=1e-12)
    np.testing.assert_allclose(f.x.array.reshape(-1, 3).sum(axis=0), forces.sum(axis=0),
                               rtol=1e-12)


def test_options_validation():
    with pytest.raises(InputError, match="max_distance"):
        EmbeddingOptions(max_distance=-1.0)
    with pytest.raises(InputError, match="max_distance_rel"):
        EmbeddingOptions(max_distance_rel=float("nan"))
