"""Connectivity of a triangle shell: edges, hinges and boundary (built once, vectorised).

Conventions (fixed for every shell module):
    * ``faces`` ``(F, 3)`` int64, consistently oriented: every interior edge is traversed in
      opposite directions by its two faces.
    * ``edges`` ``(E, 2)`` int64 with ``edges[e, 0] < edges[e, 1]``, sorted lexicographically.
    * ``edge_faces`` ``(E, 2)`` int64: ``edge_faces[e, 0]`` is the face that traverses the edge
      from its lower to its higher vertex (``i -> j``), ``edge_faces[e, 1]`` the face that
      traverses it ``j -> i``; on a boundary edge the single face is in column 0 and column 1
      is ``-1``.
    * ``face_edges`` ``(F, 3)`` int64: ``face_edges[f, a]`` is the edge from ``faces[f, a]`` to
      ``faces[f, (a + 1) % 3]``.
    * ``hinges`` ``(Hn, 4)`` int64 ``[i, j, k, l]`` for every interior edge ``(i, j)``: face0
      ``(i, j, k)`` lists the edge in its cyclic orientation as ``i -> j``; face1 contains
      ``(j, i, l)`` in its cyclic orientation. With the choice above ``(i, j) = edges[e]``
      (so ``i < j``), face0 ``= edge_faces[e, 0]``, face1 ``= edge_faces[e, 1]``, and
      ``hinge_edge[h] = e``.
    * ``boundary_edges`` ``(Eb,)`` int64 indices into ``edges`` of edges with one face.

All arrays are built with sorting / ``np.unique`` (no Python loop over faces), so a
640k-vertex shell builds in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meshes.errors import InputError


@dataclass(frozen=True, eq=False)
class ShellTopology:
    """Immutable connectivity of a consistently oriented manifold triangle mesh.

    Attributes:
        n_vertices: Number of vertices n (dofs are 3 n).
        faces: (F, 3) int64 oriented faces.
        edges: (E, 2) int64 unique edges with i < j, lexicographically sorted.
        edge_faces: (E, 2) int64 faces traversing edge i->j (col 0) and j->i (col 1, -1 on
            the boundary; a boundary edge's only face is stored in col 0).
        face_edges: (F, 3) int64 edge of face side a -> a+1.
        hinges: (Hn, 4) int64 [i, j, k, l] per interior edge (see module docstring).
        hinge_edge: (Hn,) int64 edge index of each hinge.
        boundary_edges: (Eb,) int64 edge indices with a single face.

    """

    n_vertices: int
    faces: np.ndarray
    edges: np.ndarray
    edge_faces: np.ndarray
    face_edges: np.ndarray
    hinges: np.ndarray
    hinge_edge: np.ndarray
    boundary_edges: np.ndarray

    @property
    def n_faces(self) -> int:
        """Number of faces F."""
        return int(self.faces.shape[0])

    @property
    def n_edges(self) -> int:
        """Number of edges E."""
        return int(self.edges.shape[0])

    @property
    def euler_characteristic(self) -> int:
        """V - E + F (2 for a sphere, 1 for a disc)."""
        return self.n_vertices - self.n_edges + self.n_faces

    @property
    def boundary_vertices(self) -> np.ndarray:
        """Sorted unique vertex indices on boundary edges."""
        return np.unique(self.edges[self.boundary_edges])

    @classmethod
    def from_faces(cls, faces: np.ndarray, n_vertices: int) -> ShellTopology:
        """Build the connectivity of an oriented triangle mesh.

        Args:
            faces: (F, 3) vertex indices of each triangle.
            n_vertices: Number of vertices (indices must lie in [0, n_vertices)).

        Returns:
            The topology.

        Raises:
            InputError: wrong shape, out-of-range index, degenerate face (repeated vertex),
                non-manifold edge (3+ faces, naming the edge) or inconsistent orientation
                (naming the two faces).

        """
        f = _check_faces(faces, n_vertices)
        he_from, he_to = _half_edges(f)
        edges, he_edge, counts = _edge_index(f, n_vertices)
        _check_manifold(edges, counts)
        forward = he_from < he_to
        _check_orientation(he_edge, forward, counts, he_from, he_to)
        edge_faces = _edge_faces(he_edge, forward, len(edges))
        hinges, hinge_edge = _hinges(f, edges, edge_faces)
        return cls(n_vertices=int(n_vertices), faces=f, edges=edges, edge_faces=edge_faces,
                   face_edges=he_edge.reshape(-1, 3).astype(np.int64), hinges=hinges,
                   hinge_edge=hinge_edge,
                   boundary_edges=np.flatnonzero(edge_faces[:, 1] < 0).astype(np.int64))


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) int64 unique edges ``i < j`` of triangles, lexicographically sorted.

    The same edges, in the same order, as :attr:`ShellTopology.edges`, without the
    manifold / orientation checks (any triangle soup).
    """
    f = np.asarray(faces, dtype=np.int64)
    return _edge_index(f, int(f.max()) + 1 if f.size else 0)[0]


def _half_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end vertices of the half-edges ``3 f + a``: ``faces[f, a] -> faces[f, a+1]``."""
    return faces.reshape(-1), np.roll(faces, -1, axis=1).reshape(-1)


def _edge_index(faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Find the undirected edges of the half-edges (numbered by the key ``min * n + max``).

    Returns:
        ``edges`` (E, 2) int64 with i < j, lexicographically sorted; ``he_edge`` (3F,) the
        edge of each half-edge; ``counts`` (E,) the number of half-edges on each edge.

    """
    he_from, he_to = _half_edges(faces)
    lo, hi = np.minimum(he_from, he_to), np.maximum(he_from, he_to)
    keys, he_edge, counts = np.unique(lo * n + hi, return_inverse=True, return_counts=True)
    edges = np.column_stack([keys // n, keys % n]).astype(np.int64)
    return edges, he_edge.reshape(-1), counts


def _check_faces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Validate shape, index range and non-degeneracy; return faces as C-contiguous int64."""
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise InputError(f"faces: expected a non-empty (F, 3) array, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"faces: expected integer vertex indices, got dtype {f.dtype}")
    f = np.ascontiguousarray(f, dtype=np.int64)
    bad = np.flatnonzero(((f < 0) | (f >= n_vertices)).any(axis=1))
    if bad.size:
        raise InputError(f"faces: face {bad[0]} {f[bad[0]].tolist()} has a vertex index "
                         f"outside [0, {n_vertices})")
    deg = np.flatnonzero((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0]))
    if deg.size:
        raise InputError(f"faces: face {deg[0]} {f[deg[0]].tolist()} is degenerate "
                         "(repeated vertex)")
    return f


def _check_orientation(he_edge: np.ndarray, forward: np.ndarray, counts: np.ndarray,
                       he_from: np.ndarray, he_to: np.ndarray) -> None:
    """Raise if the two faces of an interior edge traverse it in the same direction.

    ``forward`` marks half-edges running from the lower to the higher vertex; an edge with two
    faces is consistently oriented iff exactly one of its half-edges is forward.
    """
    n_forward = np.bincount(he_edge, weights=forward, minlength=counts.size)
    bad = np.flatnonzero((counts == 2) & (n_forward != 1))
    if bad.size:
        h0, h1 = np.flatnonzero(he_edge == bad[0])[:2]
        raise InputError(f"faces: faces {h0 // 3} and {h1 // 3} are inconsistently oriented "
                         f"(both traverse edge {he_from[h0]}->{he_to[h0]})")


def _check_manifold(edges: np.ndarray, counts: np.ndarray) -> None:
    """Raise naming the first edge shared by three or more faces."""
    bad = np.flatnonzero(counts > 2)
    if bad.size:
        i, j = edges[bad[0]]
        raise InputError(f"faces: non-manifold edge ({i}, {j}) is shared by "
                         f"{counts[bad[0]]} faces")


def _edge_faces(he_edge: np.ndarray, forward: np.ndarray, n_edges: int) -> np.ndarray:
    """(E, 2) faces per edge: col 0 traverses i->j (or the only face), col 1 j->i or -1."""
    ef = np.full((n_edges, 2), -1, dtype=np.int64)
    he_face = np.arange(he_edge.size, dtype=np.int64) // 3
    ef[he_edge[forward], 0] = he_face[forward]
    ef[he_edge[~forward], 1] = he_face[~forward]
    lone = ef[:, 0] < 0  # boundary edge traversed j->i only: move its face to col 0
    ef[lone, 0], ef[lone, 1] = ef[lone, 1], -1
    return ef


def _opposite_vertex(faces: np.ndarray, face: np.ndarray, a: np.ndarray,
                     b: np.ndarray) -> np.ndarray:
    """Vertex of ``faces[face]`` that is neither ``a`` nor ``b`` (vectorised)."""
    fv = faces[face]
    return fv.sum(axis=1) - a - b


def _hinges(faces: np.ndarray, edges: np.ndarray,
            edge_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hinges [i, j, k, l] and their edge indices for all interior edges."""
    he = np.flatnonzero(edge_faces[:, 1] >= 0).astype(np.int64)
    i, j = edges[he, 0], edges[he, 1]
    k = _opposite_vertex(faces, edge_faces[he, 0], i, j)
    l_ = _opposite_vertex(faces, edge_faces[he, 1], i, j)
    return np.column_stack([i, j, k, l_]).astype(np.int64), he
