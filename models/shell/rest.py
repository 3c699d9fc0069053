"""Rest state of the discrete shell: rest lengths, areas, bend angles and hinge weights.

For rest positions ``X`` (Grinspun et al. 2003):

* ``rest_lengths[e] = |X_j - X_i|`` (edge membrane W_L),
* ``rest_areas[f] = |(X_1 - X_0) x (X_2 - X_0)| / 2`` (area membrane W_A),
* ``rest_angles[h] = theta_h(X)`` by the bending module's own angle function (one orientation
  rule for rest and current angles; the rest shell is curved, so theta0 != 0),
* ``hinge_weights[h] = 3 |e0|^2 / (A1 + A2)`` (= |e0| / h0, h0 a third of the mean height),
* ``vertex_areas[v] = sum of A_f / 3`` over the faces of ``v`` (lumped, for densities).

A face whose rest area is not larger than ``1e-14 * (longest edge)^2`` is degenerate and
rejected with an :class:`InputError` naming it (never inf/NaN weights downstream). A sliver face,
whose shape quality ``q = 4 sqrt(3) A / (|e0|^2 + |e1|^2 + |e2|^2)`` (1 for an equilateral
triangle, 0 for a degenerate one) is below ``min_quality`` (default :data:`MIN_QUALITY`), is
refused too, naming the face and its quality; pass ``min_quality=0`` to allow it.

Slivers below q = 1e-3 are refused because the bending Hessian grows like 1 / q^2 and the
gradient's round-off floor then exceeds the Newton tolerance (docs/notes/flip-barrier.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from meshes.errors import InputError
from meshes.report import triangle_quality
from models.shell.bending import hinge_weights
from models.shell.dofs import check_positions
from models.shell.hinge_angle import hinge_angles
from models.shell.topology import ShellTopology

DEGENERATE_AREA_RATIO: float = 1e-14
"""A rest face with area <= this times its longest edge squared is rejected as degenerate."""

MIN_QUALITY: float = 1e-3
"""Default smallest rest quality ``4 sqrt(3) A / sum |e|^2`` accepted: below it the round-off
floor of the gradient (bending Hessian ~ 1 / q^2) exceeds a 1e-8 relative Newton tolerance (see
the module docstring)."""


@dataclass(frozen=True, eq=False)
class RestState:
    """Rest quantities of every stencil (computed once from rest positions).

    Attributes:
        positions: (n, 3) rest positions X.
        rest_lengths: (E,) rest edge lengths |e0| (same order as topology.edges).
        rest_areas: (F,) rest face areas A0.
        rest_angles: (Hn,) rest bend angles theta0 (radians, signed).
        hinge_weights: (Hn,) 3 |e0|^2 / (A1 + A2) (unit 1).
        vertex_areas: (n,) lumped vertex areas (a third of the incident face areas; 0 for an
            isolated vertex).

    """

    positions: np.ndarray
    rest_lengths: np.ndarray
    rest_areas: np.ndarray
    rest_angles: np.ndarray
    hinge_weights: np.ndarray
    vertex_areas: np.ndarray

    @classmethod
    def from_positions(cls, topology: ShellTopology, x_rest: np.ndarray,
                       min_quality: float = MIN_QUALITY) -> RestState:
        """Compute the rest state of ``topology`` at positions ``x_rest``.

        Args:
            topology: Shell connectivity.
            x_rest: (n, 3) rest positions.
            min_quality: Smallest accepted face quality ``4 sqrt(3) A / sum |e|^2`` in [0, 1)
                (0 accepts every non-degenerate face).

        Raises:
            InputError: wrong shape / non-finite positions, a degenerate rest face, or a face
                of quality below ``min_quality``.

        """
        x = check_positions(x_rest, topology.n_vertices, "x_rest")
        areas = face_areas(x, topology.faces)
        _check_degenerate(x, topology.faces, areas)
        _check_quality(x, topology.faces, min_quality)
        e = x[topology.edges[:, 1]] - x[topology.edges[:, 0]]
        return cls(positions=x.copy(), rest_lengths=np.linalg.norm(e, axis=1),
                   rest_areas=areas, rest_angles=hinge_angles(x, topology.hinges),
                   hinge_weights=hinge_weights(x, topology.hinges),
                   vertex_areas=vertex_areas(x, topology.faces, areas))


def vertex_areas(x: np.ndarray, faces: np.ndarray,
                 areas: np.ndarray | None = None) -> np.ndarray:
    """Lumped vertex areas ``sum_{f ni v} A_f / 3`` (n,) (0 for an isolated vertex).

    ``areas`` are the faces' areas when already known (else :func:`face_areas` of ``x``).
    """
    a = face_areas(x, faces) if areas is None else areas
    return np.bincount(np.ravel(faces), weights=np.repeat(a / 3.0, 3), minlength=x.shape[0])


def face_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unnormalised face normals ``(x_1 - x_0) x (x_2 - x_0)`` (F, 3) (twice the area vector)."""
    p0 = x[faces[:, 0]]
    return np.cross(x[faces[:, 1]] - p0, x[faces[:, 2]] - p0)


def area_weighted_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Sum of the incident faces' :func:`face_normals` per vertex (n, 3), not normalised."""
    n = np.zeros((x.shape[0], 3), dtype=np.float64)
    _add_corners(np.ascontiguousarray(faces, dtype=np.int64), face_normals(x, faces), n)
    return n


@njit(cache=True)
def _add_corners(faces: np.ndarray, values: np.ndarray,
                 out: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``out[faces[f, k]] += values[f]`` for k = 0, 1, 2 and f in order (``np.add.at``'s sums)."""
    for k in range(3):
        for f in range(faces.shape[0]):
            v = faces[f, k]
            for c in range(3):
                out[v, c] += values[f, c]


def vertex_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Return unit area-weighted vertex normals of a triangle mesh (n, 3)."""
    n = area_weighted_normals(x, faces)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def face_areas(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas ``|(x_1 - x_0) x (x_2 - x_0)| / 2`` (vectorised)."""
    return 0.5 * np.linalg.norm(face_normals(x, faces), axis=1)


def squared_edges(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) squared edge lengths of every face."""
    p = x[faces]
    return np.sum((p - np.roll(p, 1, axis=1)) ** 2, axis=2)


def face_quality(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Shape quality ``q = 4 sqrt(3) A / (|e0|^2 + |e1|^2 + |e2|^2)`` in [0, 1] per face.

    q = 1 for an equilateral triangle and q -> 0 for a sliver (q ~ A / l^2 when A << l^2).
    """
    return triangle_quality(x, faces)


def _check_quality(x: np.ndarray, faces: np.ndarray, min_quality: float) -> None:
    """Raise InputError naming the worst face when its quality is below ``min_quality``."""
    if not (np.isfinite(min_quality) and 0 <= min_quality < 1):
        raise InputError(f"min_quality: must be in [0, 1), got {min_quality!r}")
    q = face_quality(x, faces)
    f = int(np.argmin(q)) if q.size else 0
    if q.size and q[f] < min_quality:
        raise InputError(f"x_rest: face {f} {faces[f].tolist()} is a sliver (quality "
                         f"4 sqrt(3) A / sum |e|^2 = {q[f]:.3e} < min_quality = "
                         f"{min_quality:g}; pass min_quality=0 to allow it)")


def _check_degenerate(x: np.ndarray, faces: np.ndarray, areas: np.ndarray) -> None:
    """Raise InputError naming the first face with (numerically) zero rest area."""
    longest2 = np.max(squared_edges(x, faces), axis=1)
    bad = np.flatnonzero(~(areas > DEGENERATE_AREA_RATIO * longest2))
    if bad.size:
        f = bad[0]
        raise InputError(f"x_rest: face {f} {faces[f].tolist()} is degenerate (rest area "
                         f"{areas[f]:.3e})")
