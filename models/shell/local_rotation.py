"""Per-vertex rotations of a surface between two of its states (fitted, as in ARAP).

For each vertex ``i`` the rotation ``R_i`` that best maps its one-ring's edge vectors and its
normal from the state ``before`` to the state ``after``:

    R_i = argmin_{R in SO(3)}  sum_{j ~ i} |e'_ij - R e_ij|^2 + w_i |n'_i - R n_i|^2,

``e_ij = x_j - x_i`` in ``before``, ``e'_ij`` in ``after``, ``n_i`` the unit area-weighted
vertex normals, ``w_i = sum_j |e_ij|^2`` (the normal counts as much as the ring). The
minimiser is the rotation of ``S_i = sum_j e'_ij e_ij^T + w_i n'_i n_i^T`` in its polar
decomposition ``S_i = R_i P_i`` (``P_i`` symmetric positive definite) when ``det S_i > 0``
(Sorkine & Alexa 2007, "As-rigid-as-possible surface modeling", eq. 6, there by the SVD),
computed by Higham's scaled Newton iteration ``X <- (g X + X^{-T} / g) / 2``, ``g =
(|X^{-1}|_F / |X|_F)^{1/2}`` (Higham 1986), which converges quadratically; where ``det S_i
<= 0`` (a ring turned inside out) by Kabsch's SVD ``U diag(1, 1, det(U V^T)) V^T``. A rigid
motion of the surface gives every vertex its rotation to round-off; a translation the
identity.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from models.shell.dofs import check_positions
from models.shell.rest import vertex_normals

POLAR_ITERATIONS = 40
"""Cap on Higham's iterations (quadratic: 6-10 reach round-off from a well-conditioned S)."""


def local_rotations(before: np.ndarray, after: np.ndarray, faces: np.ndarray,
                    edges: np.ndarray) -> np.ndarray:
    """Return the fitted rotation of every vertex from ``before`` to ``after``, ``(n, 3, 3)``.

    Args:
        before: Positions ``(n, 3)`` of the first state [m].
        after: Positions ``(n, 3)`` of the second state [m].
        faces: ``(F, 3)`` oriented triangles (the normals).
        edges: ``(E, 2)`` unique edges (the one-rings).

    Returns:
        Proper rotations (orthogonal, determinant +1); the identity at a vertex whose ring
        and normal both vanish.

    """
    n = before.shape[0]
    b = check_positions(before, n, "before")
    a = check_positions(after, n, "after")
    s = _covariances(b, a, vertex_normals(b, faces), vertex_normals(a, faces),
                     np.ascontiguousarray(edges, dtype=np.int64))
    rotations, kabsch = _polar_rotations(s)
    if np.any(kabsch):  # det S <= 0: the proper rotation nearest S, by the SVD
        u, _, vt = np.linalg.svd(s[kabsch])
        u[:, :, 2] *= np.sign(np.linalg.det(u @ vt))[:, None]
        rotations[kabsch] = u @ vt
    return rotations


@njit(cache=True)
def _covariances(b: np.ndarray, a: np.ndarray, nb: np.ndarray, na: np.ndarray,
                 edges: np.ndarray) -> np.ndarray:  # pragma: no cover (compiled)
    """``S_i = sum_j e'_ij e_ij^T + w_i n'_i n_i^T`` of every vertex, ``(n, 3, 3)``."""
    n = b.shape[0]
    s = np.zeros((n, 3, 3))
    w = np.zeros(n)
    for k in range(edges.shape[0]):
        i, j = edges[k, 0], edges[k, 1]
        for r in range(3):
            ea = a[j, r] - a[i, r]
            for c in range(3):
                product = ea * (b[j, c] - b[i, c])  # the same for e_ji: both signs flip
                s[i, r, c] += product
                s[j, r, c] += product
        length = (b[j, 0] - b[i, 0]) ** 2 + (b[j, 1] - b[i, 1]) ** 2 + (b[j, 2] - b[i, 2]) ** 2
        w[i] += length
        w[j] += length
    for i in range(n):
        for r in range(3):
            for c in range(3):
                s[i, r, c] += w[i] * na[i, r] * nb[i, c]
    return s


@njit(cache=True)
def _polar_rotations(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Orthogonal polar factors of ``s`` where ``det > 0``; the others flagged for Kabsch.

    A zero matrix (no ring, no normal) gives the identity and is not flagged.
    """
    n = s.shape[0]
    out = np.zeros((n, 3, 3))
    flagged = np.zeros(n, dtype=np.bool_)
    x = np.zeros((3, 3))
    inv = np.zeros((3, 3))
    for i in range(n):
        size = 0.0
        for r in range(3):
            for c in range(3):
                size += s[i, r, c] * s[i, r, c]
        if size == 0.0:
            for r in range(3):
                out[i, r, r] = 1.0
            continue
        scale = 1.0 / np.sqrt(size)
        for r in range(3):
            for c in range(3):
                x[r, c] = s[i, r, c] * scale
        for _ in range(POLAR_ITERATIONS):
            det = (x[0, 0] * (x[1, 1] * x[2, 2] - x[1, 2] * x[2, 1])
                   - x[0, 1] * (x[1, 0] * x[2, 2] - x[1, 2] * x[2, 0])
                   + x[0, 2] * (x[1, 0] * x[2, 1] - x[1, 1] * x[2, 0]))
            if not det > 1e-30:
                flagged[i] = True
                break
            # inverse transpose = cofactor matrix / det
            inv[0, 0] = (x[1, 1] * x[2, 2] - x[1, 2] * x[2, 1]) / det
            inv[0, 1] = (x[1, 2] * x[2, 0] - x[1, 0] * x[2, 2]) / det
            inv[0, 2] = (x[1, 0] * x[2, 1] - x[1, 1] * x[2, 0]) / det
            inv[1, 0] = (x[0, 2] * x[2, 1] - x[0, 1] * x[2, 2]) / det
            inv[1, 1] = (x[0, 0] * x[2, 2] - x[0, 2] * x[2, 0]) / det
            inv[1, 2] = (x[0, 1] * x[2, 0] - x[0, 0] * x[2, 1]) / det
            inv[2, 0] = (x[0, 1] * x[1, 2] - x[0, 2] * x[1, 1]) / det
            inv[2, 1] = (x[0, 2] * x[1, 0] - x[0, 0] * x[1, 2]) / det
            inv[2, 2] = (x[0, 0] * x[1, 1] - x[0, 1] * x[1, 0]) / det
            norm_x, norm_inv = 0.0, 0.0
            for r in range(3):
                for c in range(3):
                    norm_x += x[r, c] * x[r, c]
                    norm_inv += inv[r, c] * inv[r, c]
            g = np.sqrt(np.sqrt(norm_inv / norm_x))
            change = 0.0
            for r in range(3):
                for c in range(3):
                    new = 0.5 * (g * x[r, c] + inv[r, c] / g)
                    change = max(change, abs(new - x[r, c]))
                    x[r, c] = new
            if change < 1e-15:
                break
        for r in range(3):
            for c in range(3):
                out[i, r, c] = x[r, c]
    return out, flagged


__all__ = ["POLAR_ITERATIONS", "local_rotations"]
