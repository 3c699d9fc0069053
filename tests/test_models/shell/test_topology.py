"""Topology: counts (Euler characteristic), hinge orientation convention, input errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from meshes.errors import InputError
from meshes.shells import (
    cylinder_strip,
    equilateral_plate,
    grid_plate,
    icosphere,
    irregular_plate,
)
from models.shell.topology import ShellTopology


def _cyclic_has(face: np.ndarray, a: int, b: int) -> bool:
    """True if the directed edge a->b occurs in the face's cyclic order."""
    return any(face[s] == a and face[(s + 1) % 3] == b for s in range(3))


@pytest.mark.parametrize("level", [0, 1, 3])
def test_icosphere_counts(level: int) -> None:
    p, f = icosphere(level)
    top = ShellTopology.from_faces(f, len(p))
    assert len(p) == 10 * 4**level + 2
    assert top.n_edges == 30 * 4**level and top.n_faces == 20 * 4**level
    assert top.euler_characteristic == 2
    assert top.boundary_edges.size == 0 and top.hinges.shape == (top.n_edges, 4)


@pytest.mark.parametrize("nx,ny", [(1, 1), (4, 3), (7, 6)])
def test_plate_counts(nx: int, ny: int) -> None:
    for p, f in (equilateral_plate(nx, ny), grid_plate(nx, ny, diagonals="right"),
                 grid_plate(nx, ny)):
        top = ShellTopology.from_faces(f, len(p))
        assert top.euler_characteristic == 1
        assert top.n_faces == 2 * nx * ny
        assert top.n_edges == 3 * nx * ny + nx + ny
        assert top.boundary_edges.size == 2 * (nx + ny)
        assert top.hinges.shape[0] == top.n_edges - 2 * (nx + ny)
        assert top.boundary_vertices.size == 2 * (nx + ny)


def test_irregular_and_cylinder_counts() -> None:
    for p, f in (irregular_plate(400, 3), cylinder_strip(8, 5, 1.0, 3.0, 2.0)):
        top = ShellTopology.from_faces(f, len(p))
        assert top.euler_characteristic == 1
        assert 3 * top.n_faces == 2 * top.n_edges - top.boundary_edges.size


@pytest.mark.parametrize("mesh", ["sphere", "irregular"])
def test_hinge_orientation_convention(mesh: str) -> None:
    p, f = icosphere(2) if mesh == "sphere" else irregular_plate(200, 5)
    top = ShellTopology.from_faces(f, len(p))
    i, j, k, l_ = top.hinges.T
    f0, f1 = top.edge_faces[top.hinge_edge].T
    assert np.all(i < j)
    np.testing.assert_array_equal(top.hinges[:, :2], top.edges[top.hinge_edge])
    for h in range(top.hinges.shape[0]):
        assert _cyclic_has(top.faces[f0[h]], i[h], j[h]) and k[h] in top.faces[f0[h]]
        assert _cyclic_has(top.faces[f1[h]], j[h], i[h]) and l_[h] in top.faces[f1[h]]
    assert np.all((k != i) & (k != j) & (l_ != i) & (l_ != j) & (k != l_))


def test_face_edges_and_edge_faces() -> None:
    p, f = irregular_plate(150, 2)
    top = ShellTopology.from_faces(f, len(p))
    a, b = top.faces, np.roll(top.faces, -1, axis=1)
    e = top.edges[top.face_edges]
    np.testing.assert_array_equal(np.sort(np.stack([a, b], -1), axis=-1), e)
    counts = np.bincount(top.face_edges.ravel(), minlength=top.n_edges)
    np.testing.assert_array_equal(counts, 2 - (top.edge_faces[:, 1] < 0))
    assert np.all(top.edge_faces[:, 0] >= 0)


def test_large_build_is_vectorised() -> None:
    """A 160k-vertex sphere builds in well under the time a per-face Python loop would take."""
    import time

    p, f = icosphere(7)
    t0 = time.perf_counter()
    top = ShellTopology.from_faces(f, len(p))
    elapsed = time.perf_counter() - t0
    print(f"from_faces on {len(p)} vertices: {elapsed:.2f} s")
    assert top.euler_characteristic == 2


def test_error_non_manifold() -> None:
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(InputError, match=r"non-manifold edge \(0, 1\)"):
        ShellTopology.from_faces(faces, 5)


def test_error_orientation_names_faces() -> None:
    faces = np.array([[0, 1, 2], [0, 1, 3]])  # both traverse 0->1
    with pytest.raises(InputError, match="faces 0 and 1 are inconsistently oriented"):
        ShellTopology.from_faces(faces, 4)
    p, f = irregular_plate(100, 1)
    f = f.copy()
    f[17] = f[17, ::-1]
    with pytest.raises(InputError, match="17"):
        ShellTopology.from_faces(f, len(p))


@pytest.mark.parametrize("faces,n,match", [
    ([[0, 1, 5]], 5, "outside"),
    ([[0, -1, 2]], 5, "outside"),
    ([[0, 1, 1]], 5, "degenerate"),
    ([[0, 1]], 5, "shape"),
    ([[0.0, 1.0, 2.0]], 5, "integer"),
])
def test_error_bad_faces(faces: list, n: int, match: str) -> None:
    with pytest.raises(InputError, match=match):
        ShellTopology.from_faces(np.array(faces), n)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), keep=st.floats(0.3, 1.0), flip=st.booleans())
def test_topology_invariants_random_submeshes(seed: int, keep: float, flip: bool) -> None:
    """Random face subsets of an irregular plate (optionally all faces reversed, vertices
    relabelled): incidence counts, edge-face consistency and hinge convention always hold."""
    rng = np.random.default_rng(seed)
    p, f = irregular_plate(64, seed % 7)
    f = f[rng.random(len(f)) < keep]
    if f.shape[0] == 0:
        return
    perm = rng.permutation(len(p))
    f = perm[f][:, ::-1] if flip else perm[f]
    top = ShellTopology.from_faces(f, len(p))
    n_two = int((top.edge_faces[:, 1] >= 0).sum())
    assert 3 * top.n_faces == 2 * n_two + top.boundary_edges.size
    assert top.hinges.shape[0] == n_two
    np.testing.assert_array_equal(top.hinges[:, :2], top.edges[top.hinge_edge])
    f0 = top.faces[top.edge_faces[top.hinge_edge, 0]]
    f1 = top.faces[top.edge_faces[top.hinge_edge, 1]]
    i, j, k, l_ = top.hinges.T
    assert np.all(np.sort(f0, axis=1) == np.sort(np.column_stack([i, j, k]), axis=1))
    assert np.all(np.sort(f1, axis=1) == np.sort(np.column_stack([i, j, l_]), axis=1))
    # face0 traverses i -> j: the successor of i in face0 is j
    pos = np.argmax(f0 == i[:, None], axis=1)
    assert np.all(f0[np.arange(len(pos)), (pos + 1) % 3] == j)
