"""Self-intersections of a triangle surface (models/shell/self_intersection.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from support import folded_plate as support_folded_plate

from meshes.errors import InputError
from meshes.shells import grid_plate
from models.shell.self_intersection import intersecting_faces, vertex_flags


def brute_force(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Every face pair tested, no broad phase: edge-triangle crossings by barycentric solve."""
    found = []
    for i in range(len(faces)):
        for j in range(i + 1, len(faces)):
            if np.intersect1d(faces[i], faces[j]).size:
                continue
            if any(crossing(x[f[k]], x[f[(k + 1) % 3]], x[g]) for f, g in
                   ((faces[i], faces[j]), (faces[j], faces[i])) for k in range(3)):
                found.append((i, j))
    return np.array(found, dtype=np.int64).reshape(-1, 2)


def crossing(p: np.ndarray, q: np.ndarray, tri: np.ndarray) -> bool:
    """Solve ``p + t (q - p) = a + u (b - a) + v (c - a)`` directly."""
    a, b, c = tri
    m = np.column_stack([q - p, a - b, a - c])
    if abs(np.linalg.det(m)) < 1e-14 * np.prod(np.linalg.norm(m, axis=0)):
        return False
    t, u, v = np.linalg.solve(m, a - p)
    return bool(0 <= t <= 1 and u >= 0 and v >= 0 and u + v <= 1)


def two_triangles(offset: float) -> tuple[np.ndarray, np.ndarray]:
    """A unit triangle in z = 0 and a vertical one through it, lifted by ``offset``."""
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0],
                  [0.25, 0.25, -0.5 + offset], [0.25, 0.25, 0.5 + offset], [0.25, 1.5, offset]])
    return x, np.array([[0, 1, 2], [3, 4, 5]])


def test_two_triangles_meet_until_one_is_lifted_clear() -> None:
    """The vertical triangle pierces the flat one while its lower corner is below z = 0."""
    for offset, expected in ((0.0, [[0, 1]]), (0.45, [[0, 1]]), (0.55, []), (-0.55, [])):
        x, faces = two_triangles(offset)
        assert intersecting_faces(x, faces).tolist() == expected, offset


def folded_plate(angle: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`support.folded_plate`: its positions and faces."""
    _, faces, x = support_folded_plate(angle)
    return x, faces


def test_a_plate_folded_through_itself_against_every_pair_tested() -> None:
    """Flat, folded to 170 degrees and to 180 (parallel to the other half, 0.1 above it) the
    plate has no self-intersection; folded to 200 degrees its half passes through the other
    half (from 0.29 from the hinge on). The found pairs equal those of testing every pair;
    rotating and moving the surface keeps them."""
    for degrees in (0.0, 170.0, 180.0):
        assert intersecting_faces(*folded_plate(np.radians(degrees))).shape == (0, 2), degrees
    x, faces = folded_plate(np.radians(200.0))
    found = intersecting_faces(x, faces)
    print(f"folded to 200 degrees: {len(found)} intersecting face pairs")
    assert len(found) > 20
    assert np.array_equal(found, brute_force(x, faces))
    turned = x @ Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix().T + [4.0, -2.0, 7.0]
    assert np.array_equal(intersecting_faces(turned, faces), found)


def test_random_crumpled_surface_matches_every_pair_tested(rng: np.random.Generator) -> None:
    """A 6 x 6 plate crumpled by random vertex moves of the order of its edge: the broad
    phase loses no pair of the all-pairs test."""
    x, faces = grid_plate(6, 6, 1.0, 1.0)
    for scale in (0.1, 0.3):
        moved = x + scale * rng.standard_normal(x.shape)
        found = intersecting_faces(moved, faces)
        assert np.array_equal(found, brute_force(moved, faces))
        print(f"crumpled by {scale}: {len(found)} pairs")
    assert len(found) > 0


def test_a_few_huge_faces_keep_the_grid_small_and_the_answer_the_same() -> None:
    """The folded plate plus a separate triangle 1000x its faces' size cutting through it:
    the cube size doubles until the grid lists at most ``MAX_CUBES_PER_FACE`` cubes per face
    on average, and the pairs are still those of testing every pair."""
    x, faces = folded_plate(np.radians(200.0))
    big = np.array([[-50.0, 0.31, -50.0], [60.0, 0.33, -50.0], [5.0, 0.35, 60.0]])
    x = np.vstack([x, big])
    faces = np.vstack([faces, [[len(x) - 3, len(x) - 2, len(x) - 1]]])
    found = intersecting_faces(x, faces)
    assert np.array_equal(found, brute_force(x, faces))
    assert np.count_nonzero(found[:, 1] == len(faces) - 1) > 5


def test_bad_input_is_refused_naming_it() -> None:
    x, faces = two_triangles(0.0)
    with pytest.raises(InputError, match="positions"):
        intersecting_faces(np.where(x == 1.0, np.nan, x), faces)
    with pytest.raises(InputError, match="faces"):
        intersecting_faces(x, faces + 1)


def test_vertex_flags_mark_the_corners_of_the_pairs_faces() -> None:
    x, faces = two_triangles(0.0)
    assert vertex_flags(faces, intersecting_faces(x, faces), 7).tolist() == [1, 1, 1, 1, 1, 1, 0]
    assert vertex_flags(faces, np.zeros((0, 2), dtype=np.int64), 6).tolist() == [0] * 6
