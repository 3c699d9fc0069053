"""Continuum limits of the hinge bending energy on regular lattices.

A smooth graph ``w`` with second fundamental form ``K`` sampled on a lattice: the hinge angle is
the jump of the P1 interpolant's gradient across an edge. These functions give the closed-form
energy density per lattice, the discrete sum on plates wrapped on cylinders or on spheres, and
the Richardson extrapolation of a refinement sequence (docs/notes/hinge-bending-limit.md).
"""

from __future__ import annotations

import numpy as np

from meshes.shells import equilateral_plate, grid_plate
from models.shell.bending import hinge_weights
from models.shell.hinge_angle import hinge_angles
from models.shell.topology import ShellTopology

SIZES = (8, 16, 32, 64)


def closed_form_density(lattice: str, k: np.ndarray) -> float:
    """Hand-derived limit energy density for curvature tensor k (2x2) in lattice axes."""
    a, b, c = k[0, 0], k[0, 1], k[1, 1]
    if lattice == "equilateral":
        return 3 * a * a + 3 * c * c - 2 * a * c + 8 * b * b
    if lattice == "right":
        return 3 * (a + b) ** 2 + 3 * (b + c) ** 2 + 12 * b * b
    return 3 * a * a + 3 * c * c + 12 * b * b  # alternate


def interpolant_gradient(tri: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Gradient of the P1 interpolant of w = p^T k p / 2 on a 2-D triangle (3, 2)."""
    w = 0.5 * np.einsum("pi,ij,pj->p", tri, k, tri)
    return np.linalg.solve(tri[1:] - tri[0], w[1:] - w[0])


def cell_density(tri: np.ndarray, k: np.ndarray) -> float:
    """Energy density of the periodic lattice of ``tri`` and its point reflections."""
    e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
    area = 0.5 * abs(e1[0] * e2[1] - e1[1] * e2[0])
    g = interpolant_gradient(tri, k)
    total = 0.0
    for a in range(3):
        p, q = tri[(a + 1) % 3], tri[(a + 2) % 3]
        reflected = p + q - tri  # point reflection through the edge midpoint
        edge = q - p
        m = np.array([-edge[1], edge[0]]) / np.linalg.norm(edge)
        theta = (interpolant_gradient(reflected, k) - g) @ m
        total += 3 * (edge @ edge) / (2 * area) * theta**2
    return total / (2 * area)


def richardson(values: np.ndarray, sizes: tuple[int, ...] = SIZES) -> tuple[float, float]:
    """Extrapolated limit and fitted order p of values(h = 1/size) = v + c h^p.

    Returns order ``inf`` when the values do not change (exact at every size).
    """
    diffs = np.abs(np.diff(values))
    if diffs.max() <= 1e-12 * np.abs(values).max():
        return float(values[-1]), np.inf
    p = float(np.polyfit(np.log(1.0 / np.array(sizes[1:])), np.log(diffs), 1)[0])
    ratio = sizes[-1] / sizes[-2]
    return float(values[-1] + (values[-1] - values[-2]) / (ratio**p - 1)), p


def hinge_sum(x: np.ndarray, faces: np.ndarray, rest: np.ndarray) -> float:
    """sum_h w_h theta_h^2 with weights from ``rest`` (theta0 = 0)."""
    hinges = ShellTopology.from_faces(faces, len(x)).hinges
    return float((hinge_weights(rest, hinges) * hinge_angles(x, hinges) ** 2).sum())


def plate(lattice: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit-size flat plate of the lattice with spacing 1/n, centred at the origin."""
    if lattice == "equilateral":
        p, f = equilateral_plate(n, n, 1.0 / n)
    else:
        p, f = grid_plate(n, n, 1.0, 1.0, lattice)  # type: ignore[arg-type]
    return p - p.mean(axis=0), f


def flat_area(p: np.ndarray, f: np.ndarray) -> float:
    """Total area of a flat (z = 0) triangle mesh."""
    d1, d2 = p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]
    return float(0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]).sum())


def rotate_to(p: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Proper rotation of plate points so that lattice direction ``u`` becomes the x-axis."""
    q = p.copy()
    q[:, 0] = p[:, 0] * u[0] + p[:, 1] * u[1]
    q[:, 1] = -p[:, 0] * u[1] + p[:, 1] * u[0]
    return q


def isotropic_shape_factor(points: np.ndarray, faces: np.ndarray) -> float:
    """Predicted sum_h w theta^2 / int (k1+k2)^2 for k1 = k2 from the local triangle shapes.

    For K = k I the interpolant gradient is k times the circumcentre, so theta_a = k |e_a|
    cot(alpha_a) and the cell density is 3 k^2 / (4 A^2) sum_a |e_a|^4 cot^2(alpha_a)
    (= 4 k^2 for equilateral triangles).
    """
    tri = points[faces]
    edges = [tri[:, (a + 2) % 3] - tri[:, (a + 1) % 3] for a in range(3)]  # opposite vertex a
    area = 0.5 * np.linalg.norm(np.cross(edges[0], edges[1]), axis=1)
    s = np.zeros(len(faces))
    for a in range(3):
        u, v = tri[:, (a + 1) % 3] - tri[:, a], tri[:, (a + 2) % 3] - tri[:, a]
        cot = np.einsum("ij,ij->i", u, v) / (2 * area)
        s += np.einsum("ij,ij->i", edges[a], edges[a]) ** 2 * cot**2
    return float((3 * s / (4 * area)).sum() / (4 * area.sum()))
