"""Locality-improving vertex reordering of a shell mesh, applied once before the topology.

The shell kernels (:mod:`models.shell.membrane`, :mod:`models.shell.bending`) gather the
positions of each stencil's vertices and :func:`models.shell.assembly.assemble` scatters its
blocks into the CSR rows of those vertices. Both are memory bound: when the vertices of a
stencil are far apart in memory every gather / scatter misses the cache. Mesh generators do
not care: midpoint subdivision (:func:`meshes.shells.icosphere`) appends the new vertices
level by level, so neighbours end up ``~n/2`` apart.

A :class:`VertexOrdering` is a permutation ``perm`` (new -> old: new vertex ``k`` is old vertex
``perm[k]``) with its inverse ``inverse`` (old -> new). :func:`reorder_mesh` applies it to
``(points, faces)`` and also sorts the faces by their smallest new vertex index, so that the
edges and hinges built by :meth:`models.shell.topology.ShellTopology.from_faces` (sorted by
vertex) and the faces are traversed in the same memory order as the vertices. Face rows are
only reordered, never rotated, so orientation is unchanged; all energies are sums over
stencils, hence invariant under the permutation (``W(P x) = W(x)``, gradients and Hessians
permute: ``g_new = g_old[perm]``), up to floating-point summation order.

The methods:

* ``"morton"``: sort by the Morton (Z-order) key of the rest positions quantised on a
  ``2^21`` grid per axis (Morton 1966; the standard space-filling-curve ordering for
  unstructured meshes, e.g. Bader, "Space-Filling Curves", 2013, ch. 7). O(n log n).
* ``"rcm"`` (the default): reverse Cuthill-McKee on the vertex adjacency graph
  (:func:`scipy.sparse.csgraph.reverse_cuthill_mckee`; Cuthill & McKee 1969): minimises the
  bandwidth ``max |i - j|`` over edges, so the kernels sweep a narrow band of vertices (and of
  Hessian rows) that stays in cache.
* ``"none"``: the identity.

Measured kernel times per ordering: docs/notes/vertex-ordering.md.

Output order: callers that must return data in the caller's original vertex order map it
back with :meth:`VertexOrdering.to_original` (``x_old = x_new[inverse]``) and
:meth:`VertexOrdering.to_new` for the opposite direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from meshes.errors import InputError

REORDER_METHODS: tuple[str, ...] = ("morton", "rcm", "none")
_MORTON_BITS = 21
"""Bits per axis of the Morton key (3 x 21 = 63 bits fit an int64)."""


@dataclass(frozen=True, eq=False)
class VertexOrdering:
    """A vertex permutation and its inverse.

    Attributes:
        perm: (n,) int64, new -> old: new vertex ``k`` is old vertex ``perm[k]``.
        inverse: (n,) int64, old -> new: old vertex ``v`` is new vertex ``inverse[v]``.
        method: Name of the method that produced it (:data:`REORDER_METHODS`).

    """

    perm: np.ndarray
    inverse: np.ndarray
    method: str = "none"

    @classmethod
    def from_perm(cls, perm: np.ndarray, method: str = "none") -> VertexOrdering:
        """Validate a permutation (new -> old) of ``0..n-1`` and store it with its inverse."""
        p = np.asarray(perm, dtype=np.int64)
        n = p.shape[0]
        if p.ndim != 1 or not np.array_equal(np.sort(p), np.arange(n)):
            raise InputError("perm: expected a permutation of 0..n-1")
        inverse = np.empty(n, dtype=np.int64)
        inverse[p] = np.arange(n, dtype=np.int64)
        return cls(p, inverse, method)

    @property
    def n_vertices(self) -> int:
        """Number of vertices n."""
        return int(self.perm.shape[0])

    def to_new(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex array (n, ...) in the original order -> new order (``values[perm]``)."""
        return np.asarray(values)[self.perm]

    def to_original(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex array (n, ...) in the new order -> original order (``values[inverse]``)."""
        return np.asarray(values)[self.inverse]

    def relabel(self, connectivity: np.ndarray) -> np.ndarray:
        """Old vertex indices (any shape) -> new vertex indices."""
        return self.inverse[np.asarray(connectivity, dtype=np.int64)]


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits after each of the low 21 bits of ``v`` (uint64 magic numbers)."""
    x = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF),
                        (8, 0x100F00F00F00F00F), (4, 0x10C30C30C30C30C3),
                        (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_keys(points: np.ndarray) -> np.ndarray:
    """Morton (Z-order) keys (n,) uint64 of points quantised on their bounding box.

    ``key = sum_b (bit_b(qx) << 3b) | (bit_b(qy) << 3b+1) | (bit_b(qz) << 3b+2)`` with
    ``q = floor((p - min) / extent * (2^21 - 1))``.
    """
    p = np.asarray(points, dtype=np.float64)
    lo = p.min(axis=0)
    extent = float(np.max(p.max(axis=0) - lo))
    scale = (2**_MORTON_BITS - 1) / extent if extent > 0 else 0.0
    q = np.floor((p - lo) * scale).astype(np.int64)
    return (_spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1))
            | (_spread_bits(q[:, 2]) << np.uint64(2)))


def vertex_adjacency(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Symmetric (n, n) vertex adjacency of the face edges (ones, no diagonal)."""
    f = np.asarray(faces, dtype=np.int64)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    a = sp.csr_matrix((np.ones(2 * i.size), (np.concatenate([i, j]), np.concatenate([j, i]))),
                      shape=(n_vertices, n_vertices))
    a.data[:] = 1.0
    return a


def vertex_ordering(points: np.ndarray, faces: np.ndarray,
                    method: str = "rcm") -> VertexOrdering:
    """Locality ordering of the vertices (see the module docstring for the methods).

    Args:
        points: (n, 3) rest positions.
        faces: (F, 3) int faces.
        method: "rcm" (default), "morton" or "none".

    Returns:
        The :class:`VertexOrdering`.

    Raises:
        InputError: unknown method or bad shapes.

    """
    if method not in REORDER_METHODS:
        raise InputError(f"method: expected one of {list(REORDER_METHODS)}, got {method!r}")
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points: expected an (n, 3) array, got shape {p.shape}")
    n = p.shape[0]
    if method == "morton":
        perm = np.argsort(morton_keys(p), kind="stable")
    elif method == "rcm":
        perm = reverse_cuthill_mckee(vertex_adjacency(faces, n), symmetric_mode=True)
    else:
        perm = np.arange(n)
    return VertexOrdering.from_perm(perm, method)


def reorder_mesh(points: np.ndarray, faces: np.ndarray, method: str = "rcm"
                 ) -> tuple[np.ndarray, np.ndarray, VertexOrdering]:
    """Renumber the vertices of ``(points, faces)`` for locality and sort the faces.

    Faces keep their vertex cycle (orientation); the face rows are sorted by their smallest
    new vertex index (then the other two), so face, edge and hinge traversal follow the
    vertex order.

    Args:
        points: (n, 3) positions.
        faces: (F, 3) int faces.
        method: "rcm" (default), "morton" or "none" (:func:`vertex_ordering`).

    Returns:
        ``(points_new, faces_new, ordering)`` with ``points_new = points[ordering.perm]``.

    """
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces: expected an (F, 3) array, got shape {f.shape}")
    ordering = vertex_ordering(points, f, method)
    new_faces = ordering.relabel(f)
    srt = np.sort(new_faces, axis=1)
    rows = np.lexsort((srt[:, 2], srt[:, 1], srt[:, 0]))
    return ordering.to_new(points), np.ascontiguousarray(new_faces[rows]), ordering


def edge_locality(faces: np.ndarray) -> tuple[float, int]:
    """(mean, max) of ``|i - j|`` over the face edges: average gather distance and bandwidth."""
    f = np.asarray(faces, dtype=np.int64)
    d = np.abs(f - np.roll(f, -1, axis=1))
    return float(d.mean()), int(d.max())
