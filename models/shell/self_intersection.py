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

Broad phase: a uniform grid of cubes of the faces' median bounding-box size; each face is
listed in every cube its bounding box meets, and a pair is tested once, in the lowest cube
both boxes meet, only if the boxes overlap. A face of the median size meets at most 8 cubes;
where a few large faces would list more than :data:`MAX_CUBES_PER_FACE` cubes per face on
average, the cube size is doubled until they do not, so the memory stays linear in the faces.
"""

from __future__ import annotations

import numba
import numpy as np

from meshes.errors import InputError

SINGULAR: float = 1e-14
"""Relative determinant below which an edge is taken as parallel to a triangle's plane."""

MAX_CUBES_PER_FACE: int = 16
"""Average grid cubes per face above which the broad phase doubles its cube size."""


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
def _pair_test(x: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray, a: int,
               b: int) -> bool:  # pragma: no cover - numba
    """Whether faces ``a`` and ``b`` share no vertex, have overlapping boxes and intersect."""
    f, g = faces[a], faces[b]
    for i in range(3):
        for j in range(3):
            if f[i] == g[j]:
                return False
    for k in range(3):
        if hi[a, k] < lo[b, k] or hi[b, k] < lo[a, k]:
            return False
    return _meet(x, f, g)


@numba.njit(cache=True, nogil=True)
def _grid_pairs(x: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                first_cube: np.ndarray, cube: np.ndarray, order: np.ndarray, keys: np.ndarray,
                owner: np.ndarray) -> np.ndarray:  # pragma: no cover - numba
    """Intersecting pairs from the grid's (cube, face) incidences ``cube``, ``owner``.

    ``order`` sorts the incidences by cube id, ``keys`` are the sorted ids. A pair found in
    several cubes is tested in the one whose index is the componentwise maximum of the two
    faces' ``first_cube`` (the lowest cube both boxes meet).
    """
    out = np.empty((16, 2), dtype=np.int64)
    count = 0
    start = 0
    while start < keys.size:
        stop = start
        while stop < keys.size and keys[stop] == keys[start]:
            stop += 1
        for p in range(start, stop):
            for q in range(p + 1, stop):
                a, b = owner[order[p]], owner[order[q]]
                first = True
                for k in range(3):
                    if max(first_cube[a, k], first_cube[b, k]) != cube[order[p], k]:
                        first = False
                if not first or not _pair_test(x, faces, lo, hi, a, b):
                    continue
                if count == out.shape[0]:
                    grown = np.empty((2 * count, 2), dtype=np.int64)
                    grown[:count] = out
                    out = grown
                out[count, 0], out[count, 1] = min(a, b), max(a, b)
                count += 1
        start = stop
    return out[:count]


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
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    size = float(np.median((hi - lo).max(axis=1)))
    if not size > 0.0:
        size = float((hi - lo).max()) or 1.0
    origin = lo.min(axis=0)
    while True:
        cell_lo = np.floor((lo - origin) / size).astype(np.int64)
        cell_hi = np.floor((hi - origin) / size).astype(np.int64)
        if (cell_hi - cell_lo + 1).prod(axis=1).sum() <= MAX_CUBES_PER_FACE * tri.shape[0]:
            break
        size *= 2.0
    cell, owner = _cells(cell_lo, cell_hi)
    dims = cell_hi.max(axis=0) + 1
    keys = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(keys, kind="stable")
    found = _grid_pairs(pts, tri, lo, hi, cell_lo, cell, order, keys[order], owner)
    return found[np.lexsort((found[:, 1], found[:, 0]))]


def _cells(cell_lo: np.ndarray, cell_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (cube, face) incidence: the cubes of each face's box and the face, (E, 3), (E,)."""
    extent = cell_hi - cell_lo + 1
    count = extent.prod(axis=1)
    owner = np.repeat(np.arange(cell_lo.shape[0], dtype=np.int64), count)
    rank = np.arange(owner.size, dtype=np.int64) - np.repeat(np.cumsum(count) - count, count)
    ext = extent[owner]
    offset = np.stack([rank // (ext[:, 1] * ext[:, 2]), (rank // ext[:, 2]) % ext[:, 1],
                       rank % ext[:, 2]], axis=1)
    return cell_lo[owner] + offset, owner


__all__ = ["MAX_CUBES_PER_FACE", "SINGULAR", "intersecting_faces"]
