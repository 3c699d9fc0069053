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

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from meshes.errors import InputError
from models.shell.dofs import check_positions

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
def _meet(x: np.ndarray, f: np.ndarray, g: np.ndarray) -> bool:  # pragma: no cover - numba
    """Whether an edge of face ``f`` crosses face ``g`` or one of ``g`` crosses ``f``."""
    for i in range(3):
        if _crosses(x, f[i], f[(i + 1) % 3], g[0], g[1], g[2]):
            return True
        if _crosses(x, g[i], g[(i + 1) % 3], f[0], f[1], f[2]):
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _grid_pairs(x: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                keys: np.ndarray, owner: np.ndarray, lowest: np.ndarray, begin: int,
                end: int) -> np.ndarray:  # pragma: no cover - numba
    """Intersecting pairs from the grid's (cube, face) incidences, sorted by cube id ``keys``.

    The cubes whose runs start in ``[begin, end)`` of the incidences are searched. A pair
    found in several cubes is tested in the lowest cube both boxes meet: the one where, on
    every axis, the cube is the lowest of one face or the other (``lowest``: bit ``k`` set
    where the incidence's cube is its face's lowest along axis ``k``).
    """
    out = np.empty((16, 2), dtype=np.int64)
    count = 0
    start = begin
    while start < end:
        stop = start
        while stop < keys.size and keys[stop] == keys[start]:
            stop += 1
        for p in range(start, stop):
            a = owner[p]
            for q in range(p + 1, stop):
                b = owner[q]
                if lowest[p] | lowest[q] != 7:
                    continue
                if (hi[a, 0] < lo[b, 0] or hi[b, 0] < lo[a, 0] or hi[a, 1] < lo[b, 1]
                        or hi[b, 1] < lo[a, 1] or hi[a, 2] < lo[b, 2] or hi[b, 2] < lo[a, 2]):
                    continue
                f, g = faces[a], faces[b]
                if (f[0] == g[0] or f[0] == g[1] or f[0] == g[2] or f[1] == g[0]
                        or f[1] == g[1] or f[1] == g[2] or f[2] == g[0] or f[2] == g[1]
                        or f[2] == g[2]):
                    continue
                if not _meet(x, f, g):
                    continue
                if count == out.shape[0]:
                    grown = np.empty((2 * count, 2), dtype=np.int64)
                    grown[:count] = out
                    out = grown
                out[count, 0], out[count, 1] = min(a, b), max(a, b)
                count += 1
        start = stop
    return out[:count]


def intersecting_faces(x: np.ndarray, faces: np.ndarray, threads: int = 1) -> np.ndarray:
    """Return the face pairs ``(i, j)``, ``i < j``, that share no vertex and intersect.

    Args:
        x: (n, 3) vertex positions [m].
        faces: (F, 3) int vertex indices.
        threads: Threads that search the grid's cubes (each a share of them).

    Returns:
        (P, 2) int64 array, rows sorted; empty (0, 2) for a surface free of
        self-intersections.

    Raises:
        InputError: ``x`` is not (n, 3) finite, or ``faces`` index outside it.

    """
    pts = check_positions(x, len(x), "positions")
    tri = np.ascontiguousarray(faces, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3 or (tri.size and (tri.min() < 0
                                                            or tri.max() >= pts.shape[0])):
        raise InputError(f"faces: expected (F, 3) indices below {pts.shape[0]}")
    if tri.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    lo, hi = _boxes(pts, tri)
    size = float(np.median((hi - lo).max(axis=1)))
    if not size > 0.0:
        size = float((hi - lo).max()) or 1.0
    origin = lo.min(axis=0)
    while True:
        cell_lo = np.floor((lo - origin) / size).astype(np.int64)
        cell_hi = np.floor((hi - origin) / size).astype(np.int64)
        total = int((cell_hi - cell_lo + 1).prod(axis=1).sum())
        if total <= MAX_CUBES_PER_FACE * tri.shape[0]:
            break
        size *= 2.0
    dims = cell_hi.max(axis=0) + 1
    keys, owner, lowest = _incidences(cell_lo, cell_hi, dims, total)
    order = np.argsort(keys)
    keys, owner, lowest = keys[order], owner[order], lowest[order]
    bounds = _run_bounds(keys, max(1, threads))

    def search(k: int) -> np.ndarray:
        return _grid_pairs(pts, tri, lo, hi, keys, owner, lowest, int(bounds[k]),
                           int(bounds[k + 1]))

    if len(bounds) > 2:
        with ThreadPoolExecutor(len(bounds) - 1) as pool:
            found = np.concatenate(list(pool.map(search, range(len(bounds) - 1))))
    else:
        found = search(0)
    return found[np.lexsort((found[:, 1], found[:, 0]))]


def vertex_flags(faces: np.ndarray, pairs: np.ndarray, n: int) -> np.ndarray:
    """Return (n,) floats: 1.0 at the vertices of the faces in ``pairs``, else 0.0.

    ``pairs``: (P, 2) face indices, e.g. from :func:`intersecting_faces`.
    """
    flags = np.zeros(n)
    flags[np.asarray(faces)[np.asarray(pairs, dtype=np.int64).ravel()].ravel()] = 1.0
    return flags


@numba.njit(cache=True, nogil=True)
def _boxes(x: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Lower and upper corners (F, 3) of each face's bounding box."""
    lo, hi = np.empty((faces.shape[0], 3)), np.empty((faces.shape[0], 3))
    for f in range(faces.shape[0]):
        for k in range(3):
            a, b, c = x[faces[f, 0], k], x[faces[f, 1], k], x[faces[f, 2], k]
            lo[f, k], hi[f, k] = min(a, b, c), max(a, b, c)
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _incidences(cell_lo: np.ndarray, cell_hi: np.ndarray, dims: np.ndarray,
                total: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Every (cube, face) incidence: cube id (E,), face (E,) and lowest-cube bits (E,).

    Bit ``k`` of the last is set where the cube is the face's lowest along axis ``k``.
    """
    keys = np.empty(total, dtype=np.int64)
    owner = np.empty(total, dtype=np.int64)
    lowest = np.empty(total, dtype=np.int64)
    e = 0
    for f in range(cell_lo.shape[0]):
        for i in range(cell_lo[f, 0], cell_hi[f, 0] + 1):
            for j in range(cell_lo[f, 1], cell_hi[f, 1] + 1):
                for k in range(cell_lo[f, 2], cell_hi[f, 2] + 1):
                    keys[e], owner[e] = (i * dims[1] + j) * dims[2] + k, f
                    lowest[e] = ((i == cell_lo[f, 0]) + 2 * (j == cell_lo[f, 1])
                                 + 4 * (k == cell_lo[f, 2]))
                    e += 1
    return keys, owner, lowest


def _run_bounds(keys: np.ndarray, parts: int) -> np.ndarray:
    """Split points of sorted ``keys`` into ``parts`` ranges of whole runs (first 0, last E)."""
    cuts = [0]
    for k in range(1, parts):
        at = int(np.searchsorted(keys, keys[min(k * keys.size // parts, keys.size - 1)]))
        if at > cuts[-1]:
            cuts.append(at)
    return np.array([*cuts, keys.size], dtype=np.int64)


__all__ = ["MAX_CUBES_PER_FACE", "SINGULAR", "intersecting_faces", "vertex_flags"]
