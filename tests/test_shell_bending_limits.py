"""Continuum limits of the hinge energy sum_h w_h theta_h^2 (flat rest, w = 3|e|^2/(A1+A2)).

Derivation (models/shell/bending.py docstring): for a surface with second fundamental form
K = [[A, B], [B, C]] in lattice coordinates, the hinge angle is the jump of the P1 interpolant
gradient across the edge. For a lattice made of one triangle T and its point reflections
(equilateral lattice, right-triangle grid with parallel diagonals) the energy density is the
"cell" sum over T's three edges of w_a theta_a^2 / (2 |T|), computed independently below from
the interpolants of the quadratic on T and on its reflection. Closed forms:

    equilateral:        3 A^2 + 3 C^2 - 2 A C + 8 B^2 = (k1 + k2)^2 + 2 (k1 - k2)^2,
    right grid:         3 (A + B)^2 + 3 (B + C)^2 + 12 B^2,
    alternating grid:   3 A^2 + 3 C^2 + 12 B^2            (checkerboard diagonals),
    isotropic K = k I:  3 k^2 / (4 |T|^2) sum_a |e_a|^4 cot^2(alpha_a)  (any triangle shape).

Measured limits are Richardson-extrapolated from 4 refinements with a fitted order.
"""

from __future__ import annotations

import numpy as np
import pytest

from meshes.shells import equilateral_plate, grid_plate, icosphere, wrap_on_cylinder
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


EQUILATERAL_TRI = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, np.sqrt(3) / 2]])
RIGHT_TRI = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])  # grid_plate(..., "right") cell


@pytest.mark.parametrize("lattice,tri", [("equilateral", EQUILATERAL_TRI),
                                         ("right", RIGHT_TRI)])
def test_closed_forms_match_generic_cell_computation(lattice: str, tri: np.ndarray,
                                                     rng) -> None:
    for _ in range(5):
        k = rng.standard_normal((2, 2))
        k = k + k.T
        assert cell_density(tri, k) == pytest.approx(closed_form_density(lattice, k), rel=1e-12)
    # equilateral: isotropic, (k1 + k2)^2 + 2 (k1 - k2)^2 in principal curvatures
    k1, k2 = 0.7, -0.3
    rot = np.array([[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]])
    k = rot @ np.diag([k1, k2]) @ rot.T
    if lattice == "equilateral":
        assert cell_density(tri, k) == pytest.approx((k1 + k2) ** 2 + 2 * (k1 - k2) ** 2)


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


CYLINDER_CASES = [("equilateral", 0.0, 3.0), ("equilateral", 90.0, 3.0),
                  ("equilateral", 17.0, 3.0), ("right", 0.0, 3.0), ("right", 45.0, 9.0),
                  ("right", -45.0, 3.0), ("alternate", 0.0, 3.0), ("alternate", 45.0, 4.5)]


@pytest.mark.parametrize("lattice,angle,expected", CYLINDER_CASES)
def test_cylinder_limit(lattice: str, angle: float, expected: float) -> None:
    """Plate rolled on a cylinder (R = 1) bent along lattice direction ``angle`` (deg)."""
    u = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle))])
    predicted = closed_form_density(lattice, np.outer(u, u))
    assert predicted == pytest.approx(expected, rel=1e-14)
    ratios = []
    for n in SIZES:
        p, f = plate(lattice, n)
        q = rotate_to(p, u)
        ratios.append(hinge_sum(wrap_on_cylinder(q, 1.0), f, q) / flat_area(p, f))
    limit, order = richardson(np.array(ratios))
    print(f"cylinder {lattice:11s} bent at {angle:5.1f} deg: ratios "
          + " ".join(f"{r:.5f}" for r in ratios)
          + f" -> {limit:.5f} (order {order:.2f}), predicted {predicted}")
    assert limit == pytest.approx(predicted, rel=3e-3)
    assert 0.7 <= order <= 1.3 or order == np.inf  # missing boundary hinges: O(h)


@pytest.mark.parametrize("lattice", ["equilateral", "right", "alternate"])
def test_small_quadratic_graph_limit_full_tensor(lattice: str) -> None:
    """z = eps/2 p^T K p with sphere-like, saddle and twist parts (small slope)."""
    k = np.array([[1.0, 0.6], [0.6, -0.4]])
    eps = 1e-4
    ratios = []
    for n in SIZES:
        p, f = plate(lattice, n)
        x = p.copy()
        x[:, 2] = 0.5 * eps * np.einsum("pi,ij,pj->p", p[:, :2], k, p[:, :2])
        ratios.append(hinge_sum(x, f, p) / (eps**2 * flat_area(p, f)))
    limit, order = richardson(np.array(ratios))
    predicted = closed_form_density(lattice, k)
    print(f"quadratic graph {lattice:11s}: " + " ".join(f"{r:.5f}" for r in ratios)
          + f" -> {limit:.5f} (order {order:.2f}), predicted {predicted:.5f}")
    assert limit == pytest.approx(predicted, rel=3e-3)


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


def test_sphere_limit_from_triangle_shapes() -> None:
    """Icosphere R = 2: sum_h w theta^2 vs int (k1+k2)^2 dA = 16 pi (R-independent)."""
    levels = (5, 6, 7)
    ratios = []
    for level in levels:
        p, f = icosphere(level, radius=2.0)
        ratios.append(hinge_sum(p, f, p) / (16 * np.pi))
    limit, order = richardson(np.array(ratios), tuple(2**lv for lv in levels))
    predicted = isotropic_shape_factor(*icosphere(levels[-1], radius=2.0))
    print("icosphere levels 5-7: " + " ".join(f"{r:.6f}" for r in ratios)
          + f" -> {limit:.6f} (order {order:.2f}); triangle-shape prediction {predicted:.6f}")
    assert limit == pytest.approx(predicted, abs=2e-4)
    assert 0.01 < limit - 1.0 < 0.02  # an icosphere is not equilateral: 1.6 % above 16 pi
