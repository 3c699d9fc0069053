"""Cap slivers flipped out of the shell's coarse surface (models/embedding/caps.py)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from support import EXTERNAL_MESHES

from meshes.loader import load
from meshes.report import triangle_quality
from models.embedding.caps import CAP_QUALITY, flip_caps
from models.embedding.surface import Surface, boundary_surface, canonical_faces, signed_volume


def surface(vertices: list[list[float]], faces: list[list[int]]) -> Surface:
    v = np.array(vertices, dtype=np.float64)
    return Surface(vertices=v, faces=np.array(faces, dtype=np.int64),
                   node_map=np.arange(v.shape[0], dtype=np.int64))


def normals(s: Surface) -> np.ndarray:
    v, f = s.vertices, s.faces
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def test_a_cap_and_its_neighbour_become_the_quadrilateral_s_other_diagonal():
    """Apex c 0.01 over the long edge ab (q = 0.035), the neighbour's apex d below: the flip
    gives (a, d, c), (d, b, c), both facing +z as before, the worst quality 0.035 -> 0.50,
    and reports the cap's height as the surface's largest move."""
    s = surface([[0, 0, 0], [1, 0, 0], [0.5, 0.01, 0], [0.5, -0.8, 0]], [[0, 1, 2], [1, 0, 3]])
    out = flip_caps(s)
    assert out.flips == 1
    np.testing.assert_array_equal(out.surface.faces, canonical_faces(np.array([[0, 3, 2],
                                                                               [3, 1, 2]])))
    np.testing.assert_array_equal(out.surface.vertices, s.vertices)
    assert np.all(normals(out.surface)[:, 2] > 0)
    assert out.quality_before == pytest.approx(triangle_quality(s.vertices, s.faces).min())
    assert out.quality_before < 0.04 and out.quality_after > 0.5
    assert out.moved == pytest.approx(0.01, rel=1e-12)


def test_a_surface_without_caps_is_returned_as_it_is():
    s = surface([[0, 0, 0], [1, 0, 0], [0.5, 0.8, 0], [0.5, -0.8, 0]], [[0, 1, 2], [1, 0, 3]])
    out = flip_caps(s)
    assert out.surface is s and out.flips == 0 and out.moved == 0.0


def test_no_flip_that_turns_a_face_over_or_repeats_an_edge():
    """A planar pair whose flip would improve the worse quality (0.020 -> 0.045) but turn
    (d, b, c) over is kept; so is a cap on a tetrahedron, where the new diagonal exists."""
    turning = surface([[0, 0, 0], [1, 0, 0], [0.9, 0.02, 0], [1.5, -0.02, 0]],
                      [[0, 1, 2], [1, 0, 3]])
    new = np.array([[0, 3, 2], [3, 1, 2]])
    assert triangle_quality(turning.vertices, new).min() > \
        triangle_quality(turning.vertices, turning.faces).min()
    assert flip_caps(turning).flips == 0
    points = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0.01, 0], [0.5, 0.3, 0.5]], dtype=np.float64)
    tet = boundary_surface(points, np.array([[0, 1, 2, 3]]))
    assert triangle_quality(tet.vertices, tet.faces).min() < CAP_QUALITY
    assert flip_caps(tet).flips == 0


def test_the_bunny_loses_its_ten_caps_and_stays_a_closed_oriented_surface():
    """IPC's bunny: 10 faces below q = 0.1 (worst 0.0352) flipped, worst 0.111 after; every
    directed edge once with its reverse, the same vertices, Euler characteristic and face
    count, the enclosed volume within the flipped caps' reach."""
    mesh = load(EXTERNAL_MESHES / "ipc_bunny.msh")
    s = boundary_surface(mesh.points, mesh.tets)
    out = flip_caps(s)
    assert out.flips == 10
    assert out.quality_before == pytest.approx(0.0352, abs=5e-5)
    assert out.quality_after == pytest.approx(0.1109, abs=5e-5)
    assert out.quality_after == pytest.approx(
        triangle_quality(out.surface.vertices, out.surface.faces).min(), rel=1e-14)
    f = out.surface.faces
    edges = Counter((int(x[k]), int(x[(k + 1) % 3])) for x in f for k in range(3))
    assert max(edges.values()) == 1 and all((b, a) in edges for a, b in edges)
    assert f.shape == s.faces.shape and len(edges) == 3 * f.shape[0]
    np.testing.assert_array_equal(out.surface.vertices, s.vertices)
    np.testing.assert_array_equal(out.surface.node_map, s.node_map)
    assert 0.0 < out.moved < 0.01
    volume = signed_volume(s.vertices, s.faces)
    assert signed_volume(out.surface.vertices, f) == pytest.approx(volume, rel=1e-3)


def test_no_flip_touches_an_edge_of_more_than_two_faces():
    """Two tets touching by the edge 0-1: the cap (0, 2, 1) across it (q = 0.023) would flip
    with a face of the other tet and join the two surfaces; it is kept."""
    points = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0.01, 0], [0.5, 0.3, 0.5], [0.5, -0.3, -0.6],
                       [0.4, -0.6, 0.3]], dtype=np.float64)
    s = boundary_surface(points, np.array([[0, 1, 2, 3], [0, 1, 4, 5]]))
    assert triangle_quality(s.vertices, s.faces).min() < 0.03
    out = flip_caps(s)
    assert out.flips == 0 and out.surface is s
