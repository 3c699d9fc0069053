"""Per-vertex rotations fitted between two states of a surface (models/shell/local_rotation.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from meshes.errors import InputError
from meshes.shells import grid_plate, icosphere
from models.shell.local_rotation import local_rotations
from models.shell.topology import ShellTopology


def surface(kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x, faces, edges)`` of an open plate or a closed sphere."""
    x, faces = grid_plate(6, 5) if kind == "plate" else icosphere(2)
    return x, faces, ShellTopology.from_faces(faces, x.shape[0]).edges


@pytest.mark.parametrize("kind", ["plate", "sphere"])
def test_a_rigid_motion_gives_every_vertex_its_rotation(kind) -> None:
    """Rotated by 70 degrees about a tilted axis and translated: R_i = R at every vertex, to
    round-off; translated only: the identity."""
    x, faces, edges = surface(kind)
    rot = Rotation.from_rotvec(70.0 * np.pi / 180.0 * np.array([1.0, 2.0, -0.5])
                               / np.linalg.norm([1.0, 2.0, -0.5])).as_matrix()
    moved = x @ rot.T + np.array([0.3, -2.0, 5.0])
    assert np.abs(local_rotations(x, moved, faces, edges) - rot).max() < 1e-13
    assert np.abs(local_rotations(x, x + 1.0, faces, edges) - np.eye(3)).max() < 1e-14


def test_a_bent_plate_turns_each_vertex_with_its_own_part() -> None:
    """A plate bent about the line x = 0.5 (its right half turned by 40 degrees about y): the
    vertices inside each half get that half's rotation; every fitted matrix is a proper
    rotation; a non-uniform stretch gives rotations too (orthogonal, det +1)."""
    x, faces, edges = surface("plate")
    angle = np.deg2rad(40.0)
    rot = Rotation.from_rotvec([0.0, angle, 0.0]).as_matrix()
    right = x[:, 0] > 0.5 + 1e-12
    bent = x.copy()
    bent[right] = (x[right] - [0.5, 0.0, 0.0]) @ rot.T + [0.5, 0.0, 0.0]
    r = local_rotations(x, bent, faces, edges)
    inner_left, inner_right = x[:, 0] < 0.3, x[:, 0] > 0.7
    assert np.abs(r[inner_left] - np.eye(3)).max() < 1e-13
    assert np.abs(r[inner_right] - rot).max() < 1e-13
    stretched = bent * np.array([1.3, 0.8, 1.0]) + 0.01 * np.sin(7.0 * x[:, [1, 2, 0]])
    for m in (r, local_rotations(x, stretched, faces, edges)):
        assert np.abs(np.einsum("nij,nkj->nik", m, m) - np.eye(3)).max() < 1e-12
        assert np.allclose(np.linalg.det(m), 1.0, rtol=0, atol=1e-12)


def test_a_surface_collapsed_or_mirrored_still_gets_proper_rotations() -> None:
    """The sphere collapsed onto a line (every covariance of rank one, ``det S = 0``: Kabsch's
    branch) and mirrored through a plane: every vertex gets a proper rotation, orthogonal
    with determinant +1 (a polar factor of the collapsed covariance does not exist)."""
    from models.shell import local_rotation

    x, faces, edges = surface("sphere")
    line = x * np.array([1.0, 0.0, 0.0])
    s = local_rotation._covariances(x, line, np.zeros_like(x), np.zeros_like(x), edges)
    assert np.all(local_rotation._polar_rotations(s)[1])  # all flagged for Kabsch
    for after in (line, x * np.array([-1.0, 1.0, 1.0])):
        r = local_rotations(x, after, faces, edges)
        assert np.abs(np.einsum("nij,nkj->nik", r, r) - np.eye(3)).max() < 1e-12
        assert np.allclose(np.linalg.det(r), 1.0, rtol=0, atol=1e-12)


def test_the_states_must_be_the_surfaces_positions() -> None:
    """A state of another vertex count or with a NaN is refused, naming it."""
    x, faces, edges = surface("plate")
    with pytest.raises(InputError, match="after"):
        local_rotations(x, x[:-1], faces, edges)
    bad = x.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="before"):
        local_rotations(bad, x, faces, edges)


def test_vertex_normals_are_the_area_weighted_sums_of_their_faces() -> None:
    """The compiled corner sums equal ``np.add.at``'s bit for bit (same order of additions):
    the rest normals, and with them every run's imperfection, are those of before; each
    normal is unit and, on the sphere, the outward radial direction to 2e-2 at level 3
    (measured 1.1e-2)."""
    from meshes.shells import irregular_plate
    from models.shell.rest import area_weighted_normals, face_normals, vertex_normals

    for x, faces in (irregular_plate(12, seed=3), icosphere(3)):
        x = x + 0.01 * np.random.default_rng(1).standard_normal(x.shape)
        expected = np.zeros_like(x)
        for corner in range(3):
            np.add.at(expected, faces[:, corner], face_normals(x, faces))
        assert np.array_equal(area_weighted_normals(x, faces), expected)
        assert np.allclose(np.linalg.norm(vertex_normals(x, faces), axis=1), 1.0)
    x, faces = icosphere(3)
    radial = x / np.linalg.norm(x, axis=1, keepdims=True)
    assert np.abs(vertex_normals(x, faces) - radial).max() < 2e-2
