"""Self-intersections of the shell surface: face pairs that pass through each other.

The shell energy has no contact between faces that share no hinge: the flip barrier
(:mod:`models.shell.barrier`) keeps each face from turning over against its reference and the
fold contact (:mod:`models.shell.bending`) keeps a hinge's two faces apart, but a fold pressed
onto its non-adjacent neighbours can pass through them (docs/notes/flip-barrier.md). This
module measures that, so a frame's record says whether its minimiser is a physical skin.

Two faces ``T_i``, ``T_j`` that share no vertex intersect when an edge of one crosses the
other: for some edge ``p + t d`` (``t`` in [0, 1]) of one and the other's corners ``a, b, c``,

    p + t d = a + u (b - a) + v (c - a),   u >= 0, v >= 0, u + v <= 1,

solved by Moller & Trumbore (1997), "Fast, minimum storage ray-triangle intersection". Any
transversal intersection of two triangles has such a crossing edge (their intersection segment
ends on an edge of one of them). Coplanar overlaps (the system singular, ``|det| <= 1e-14
|d| |b - a| |c - a|``) are not counted: they have measure zero under motion. Faces sharing a
vertex are never reported; their overlap is the barriers' business.

Broad phase: ``T_i`` and ``T_j`` can only meet if their centroids are at most ``r_i + r_j``
apart, ``r`` the largest centroid-to-corner distance; pairs within twice the largest ``r``
come from a k-d tree (:class:`scipy.spatial.cKDTree`), the narrow phase runs over them.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from meshes.errors import InputError

SINGULAR: float = 1e-14
"""Relative determinant below which an edge is taken as parallel to a triangle's plane."""


@numba.njit(cache=True, nogil=True, inline="always")
def _sub(x: np.ndarray, i: int, j: int) -> tuple[float, float, float]:  # pragma: no cover
    """``x_i - x_j`` as three scalars."""
    return x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]


@numba.njit(cache=True, nogil=True)
def _crosses(x: np.ndarray, p: int, q: int, a: int, b: int,
             c: int) -> bool:  # pragma: no cover - numba
    """Whether the segment ``x_p x_q`` meets the closed triangle ``x_a x_b x_c``."""
    d0, d1, d2 = _sub(x, q, p)
    e0, e1, e2 = _sub(x, b, a)
    f0, f1, f2 = _sub(x, c, a)
    h0, h1, h2 = d1 * f2 - d2 * f1, d2 * f0 - d0 * f2, d0 * f1 - d1 * f0  # d x f
    det = e0 * h0 + e1 * h1 + e2 * h2
    scale = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2) * (e0 * e0 + e1 * e1 + e2 * e2)
                    * (f0 * f0 + f1 * f1 + f2 * f2))
    if abs(det) <= SINGULAR * scale:
        return False
    s0, s1, s2 = _sub(x, p, a)
    u = (s0 * h0 + s1 * h1 + s2 * h2) / det
    if u < 0.0 or u > 1.0:
        return False
    r0, r1, r2 = s1 * e2 - s2 * e1, s2 * e0 - s0 * e2, s0 * e1 - s1 * e0  # s x e
    v = (d0 * r0 + d1 * r1 + d2 * r2) / det
    if v < 0.0 or u + v > 1.0:
        return False
    t = (f0 * r0 + f1 * r1 + f2 * r2) / det
    return 0.0 <= t <= 1.0


@numba.njit(cache=True, nogil=True)
def _boxes_apart(x: np.ndarray, f: np.ndarray, g: np.ndarray) -> bool:  # pragma: no cover
    """Whether the bounding boxes of the faces ``f`` and ``g`` are disjoint."""
    for k in range(3):
        lo_f = min(x[f[0], k], x[f[1], k], x[f[2], k])
        hi_f = max(x[f[0], k], x[f[1], k], x[f[2], k])
        lo_g = min(x[g[0], k], x[g[1], k], x[g[2], k])
        hi_g = max(x[g[0], k], x[g[1], k], x[g[2], k])
        if hi_f < lo_g or hi_g < lo_f:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _meet(x: np.ndarray, f: np.ndarray, g: np.ndarray) -> bool:  # pragma: no cover - numba
    """Whether an edge of face ``f`` crosses face ``g`` or one of ``g`` crosses ``f``."""
    for i in range(3):
        if _crosses(x, f[i], f[(i + 1) % 3], g[0], g[1], g[2]):
            return True
        if _crosses(x, g[i], g[(i + 1) % 3], f[0], f[1], f[2]):
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _narrow(x: np.ndarray, faces: np.ndarray, pairs: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Mask of the candidate pairs whose faces share no vertex and intersect."""
    hit = np.zeros(pairs.shape[0], dtype=np.bool_)
    for k in range(pairs.shape[0]):
        f, g = faces[pairs[k, 0]], faces[pairs[k, 1]]
        shared = False
        for i in range(3):
            for j in range(3):
                shared |= f[i] == g[j]
        if not shared and not _boxes_apart(x, f, g):
            hit[k] = _meet(x, f, g)
    return hit


def intersecting_faces(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Return the face pairs ``(i, j)``, ``i < j``, that share no vertex and intersect.

    Args:
        x: (n, 3) vertex positions [m].
        faces: (F, 3) int vertex indices.

    Returns:
        (P, 2) int64 array, rows sorted; empty (0, 2) for a surface free of
        self-intersections.

    Raises:
        InputError: ``x`` is not (n, 3) finite, or ``faces`` index outside it.

    """
    pts = np.ascontiguousarray(x, dtype=np.float64)
    tri = np.ascontiguousarray(faces, dtype=np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise InputError(f"positions: expected (n, 3) finite floats, got shape {pts.shape}")
    if tri.ndim != 2 or tri.shape[1] != 3 or (tri.size and (tri.min() < 0
                                                            or tri.max() >= pts.shape[0])):
        raise InputError(f"faces: expected (F, 3) indices below {pts.shape[0]}")
    if tri.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    corners = pts[tri]
    centroid = corners.mean(axis=1)
    reach = float(np.linalg.norm(corners - centroid[:, None], axis=2).max())
    pairs = cKDTree(centroid).query_pairs(2.0 * reach, output_type="ndarray").astype(np.int64)
    if pairs.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.sort(pairs, axis=1)
    found = pairs[_narrow(pts, tri, pairs)]
    return found[np.lexsort((found[:, 1], found[:, 0]))]


__all__ = ["SINGULAR", "intersecting_faces"]
