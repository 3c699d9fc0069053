"""Rest state of the discrete shell: rest lengths, areas, bend angles and hinge weights.

For rest positions ``X`` (Grinspun et al. 2003):

* ``rest_lengths[e] = |X_j - X_i|`` (edge membrane W_L),
* ``rest_areas[f] = |(X_1 - X_0) x (X_2 - X_0)| / 2`` (area membrane W_A),
* ``rest_angles[h] = theta_h(X)`` by the bending module's own angle function (one orientation
  rule for rest and current angles; the rest shell is curved, so theta0 != 0),
* ``hinge_weights[h] = 3 |e0|^2 / (A1 + A2)`` (= |e0| / h0, h0 a third of the mean height),
* ``vertex_areas[v] = sum of A_f / 3`` over the faces of ``v`` (lumped, for densities).

A face whose rest area is not larger than ``1e-14 * (longest edge)^2`` is degenerate and
rejected with an :class:`InputError` naming it (never inf/NaN weights downstream).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.errors import InputError
from models.shell.bending import hinge_weights
from models.shell.dofs import check_positions
from models.shell.hinge_angle import hinge_angles
from models.shell.topology import ShellTopology

DEGENERATE_AREA_RATIO: float = 1e-14
"""A rest face with area <= this times its longest edge squared is rejected as degenerate."""


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
    def from_positions(cls, topology: ShellTopology, x_rest: np.ndarray) -> RestState:
        """Compute the rest state of ``topology`` at positions ``x_rest``.

        Raises:
            InputError: wrong shape / non-finite positions, or a degenerate rest face.

        """
        x = check_positions(x_rest, topology.n_vertices, "x_rest")
        areas = face_areas(x, topology.faces)
        _check_degenerate(x, topology.faces, areas)
        e = x[topology.edges[:, 1]] - x[topology.edges[:, 0]]
        vertex_areas = np.bincount(topology.faces.ravel(), weights=np.repeat(areas / 3.0, 3),
                                   minlength=topology.n_vertices)
        return cls(positions=x.copy(), rest_lengths=np.linalg.norm(e, axis=1),
                   rest_areas=areas, rest_angles=hinge_angles(x, topology.hinges),
                   hinge_weights=hinge_weights(x, topology.hinges), vertex_areas=vertex_areas)


def face_areas(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas ``|(x_1 - x_0) x (x_2 - x_0)| / 2`` (vectorised)."""
    p0 = x[faces[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(x[faces[:, 1]] - p0, x[faces[:, 2]] - p0), axis=1)


def _check_degenerate(x: np.ndarray, faces: np.ndarray, areas: np.ndarray) -> None:
    """Raise InputError naming the first face with (numerically) zero rest area."""
    p = x[faces]
    longest2 = np.max(np.sum((p - np.roll(p, 1, axis=1)) ** 2, axis=2), axis=1)
    bad = np.flatnonzero(~(areas > DEGENERATE_AREA_RATIO * longest2))
    if bad.size:
        f = bad[0]
        raise InputError(f"x_rest: face {f} {faces[f].tolist()} is degenerate (rest area "
                         f"{areas[f]:.3e})")
