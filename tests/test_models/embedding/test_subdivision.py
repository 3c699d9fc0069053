"""Linear and Loop subdivision as sparse matrices: counts, closedness, orientation, smoothness."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError
from meshes.shells import equilateral_plate, icosphere
from meshes.structured import structured_box
from models.embedding.subdivision import (
    SubdivisionOptions,
    edge_topology,
    loop_beta,
    subdivide,
)
from models.embedding.surface import boundary_surface, signed_volume

SCHEMES = [("linear", "warren"), ("loop", "warren"), ("loop", "loop")]


def box_surface():
    """Outward boundary surface of a 2x3x2 Kuhn box (irregular valences 3..8)."""
    m = structured_box((2, 3, 2), size=(1.0, 1.5, 1.0))
    s = boundary_surface(m.points, m.tets)
    return s.vertices, s.faces


def max_bend_angle(v, f):
    """Largest angle between the normals of two faces sharing an edge."""
    topo = edge_topology(f, v.shape[0])
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    order = np.argsort(topo.face_edges.reshape(-1), kind="stable")
    faces_of_edge = (order // 3).reshape(-1, 2)  # closed mesh: every edge has 2 faces
    cos = np.einsum("ij,ij->i", n[faces_of_edge[:, 0]], n[faces_of_edge[:, 1]])
    return float(np.arccos(np.clip(cos, -1.0, 1.0)).max())


@pytest.mark.parametrize("scheme,beta", SCHEMES)
@pytest.mark.parametrize("surface", ["icosahedron", "box"])
def test_counts_closed_rows_and_product(scheme, beta, surface):
    v0, f0 = icosphere(0) if surface == "icosahedron" else box_surface()
    sub = subdivide(v0, f0, SubdivisionOptions(levels=3, scheme=scheme, beta=beta))
    v = v0
    for s, f, f_next in zip(sub.matrices, sub.face_levels[:-1], sub.face_levels[1:],
                            strict=True):
        topo = edge_topology(f, v.shape[0])
        assert s.shape == (v.shape[0] + topo.edges.shape[0], v.shape[0])  # V' = V + E
        assert f_next.shape[0] == 4 * f.shape[0]  # F' = 4 F
        assert np.abs(np.asarray(s.sum(axis=1)).ravel() - 1.0).max() < 1e-14
        v = s @ v
        assert np.all(edge_topology(f_next, v.shape[0]).edge_faces == 2)  # still closed
    assert np.abs(sub.prolongation @ v0 - sub.vertices).max() < 1e-13
    assert np.array_equal(v, sub.vertices)


@pytest.mark.parametrize("scheme,beta", SCHEMES)
@pytest.mark.parametrize("surface", ["icosahedron", "box"])
def test_orientation_and_signed_volume(scheme, beta, surface):
    v0, f0 = icosphere(0) if surface == "icosahedron" else box_surface()
    vol0 = signed_volume(v0, f0)
    assert vol0 > 0.0
    vols = [signed_volume(sub.vertices, sub.faces) for sub in
            (subdivide(v0, f0, SubdivisionOptions(levels=k, scheme=scheme, beta=beta))
             for k in (1, 2, 3))]
    if scheme == "linear":
        np.testing.assert_allclose(vols, vol0, rtol=1e-13)
    else:  # Loop shrinks a convex body but never flips it
        assert all(0.0 < w < vol0 for w in vols)
        assert vols[0] > vols[1] > vols[2]


def predicted_angle_ratio(valences, beta):
    """Asymptotic per-level ratio of the largest dihedral angle under Loop subdivision.

    At a vertex of valence k the local subdivision matrix has the subdominant eigenvalue
    lambda_1 = 3/8 + cos(2 pi / k) / 4 (tangent plane) and lambda_2 = 5/8 - k beta (the
    vertex rule's own mode); normals converge like lambda_2 / lambda_1 (bounded curvature
    needs lambda_2 = lambda_1^2, Loop's beta). Regular regions halve the angle (1/2).
    """
    k = np.asarray(valences, dtype=float)
    lam1 = 3 / 8 + np.cos(2 * np.pi / k) / 4
    lam2 = 5 / 8 - k * loop_beta(k.astype(int), beta)
    return max(0.5, float(np.max(lam2 / lam1)))


@pytest.mark.parametrize("beta", ["warren", "loop"])
@pytest.mark.parametrize("surface", ["icosahedron", "box"])
def test_loop_limit_is_smooth(beta, surface):
    v0, f0 = icosphere(0) if surface == "icosahedron" else box_surface()
    valences = np.unique(np.bincount(edge_topology(f0, v0.shape[0]).edges.ravel()))
    levels = range(1, 7)
    angles = np.array([max_bend_angle(s.vertices, s.faces) for s in
                       (subdivide(v0, f0, SubdivisionOptions(levels=k, scheme="loop", beta=beta))
                        for k in levels)])
    assert np.all(np.diff(angles) < 0.0), angles  # the max bend angle drops every level
    measured = np.log2(angles[-1] / angles[-2])
    predicted = np.log2(predicted_angle_ratio(valences, beta))
    assert abs(measured - predicted) < 0.03, (measured, predicted, angles)
    lin = subdivide(v0, f0, SubdivisionOptions(levels=3, scheme="linear"))
    assert max_bend_angle(lin.vertices, lin.faces) == pytest.approx(max_bend_angle(v0, f0),
                                                                    abs=1e-12)


def test_beta_analytic_values():
    k = np.array([3, 4, 5, 6, 7])
    np.testing.assert_allclose(loop_beta(k, "warren"), [3 / 16, 3 / 32, 3 / 40, 1 / 16, 3 / 56],
                               rtol=1e-15)
    loop = loop_beta(k, "loop")
    assert loop[3] == pytest.approx(1 / 16, rel=1e-14)  # regular vertex: both rules agree
    assert loop[0] == pytest.approx((5 / 8 - (3 / 8 - 1 / 8) ** 2) / 3, rel=1e-14)


@pytest.mark.parametrize("scheme", ["linear", "loop"])
def test_open_surface_boundary_rules(scheme):
    v0, f0 = equilateral_plate(4, 3)
    sub = subdivide(v0, f0, SubdivisionOptions(levels=2, scheme=scheme))
    t0 = edge_topology(f0, v0.shape[0])
    t2 = edge_topology(sub.faces, sub.vertices.shape[0])
    n_b0 = int(np.count_nonzero(t0.edge_faces == 1))
    assert np.count_nonzero(t2.edge_faces == 1) == 4 * n_b0  # each boundary edge splits in 2
    euler = sub.vertices.shape[0] - t2.edges.shape[0] + sub.faces.shape[0]
    assert euler == 1  # still a disk
    # boundary curve only depends on boundary vertices (cubic B-spline / midpoint rule)
    s = subdivide(v0, f0, SubdivisionOptions(levels=1, scheme=scheme)).matrices[0].tocoo()
    t1 = edge_topology(sub.face_levels[1], s.shape[0])
    on_b0 = np.zeros(v0.shape[0], bool)
    on_b0[t0.edges[t0.edge_faces == 1].ravel()] = True
    on_b1 = np.zeros(s.shape[0], bool)
    on_b1[t1.edges[t1.edge_faces == 1].ravel()] = True
    assert np.all(on_b0[s.col[on_b1[s.row]]])
    if scheme == "loop":  # boundary vertex: 3/4 self + 1/8 per boundary neighbour (or corner)
        d = s.tocsr().diagonal()[:v0.shape[0]]
        assert set(np.round(d[on_b0], 12)) <= {0.75, 1.0}


def test_non_manifold_edge_raises():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(InputError, match="edge \\(0, 1\\)"):
        subdivide(v, f)


def test_options_validation():
    with pytest.raises(InputError, match="levels"):
        SubdivisionOptions(levels=-1)
    with pytest.raises(InputError, match="scheme"):
        SubdivisionOptions(scheme="butterfly")  # type: ignore[arg-type]
