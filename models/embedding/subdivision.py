"""Linear (1-to-4 midpoint) and Loop subdivision as sparse matrices (pure numpy/scipy).

One level maps ``n_l`` vertices and ``m_l`` faces to ``n_{l+1} = n_l + E_l`` vertices (one new
vertex per edge, numbered ``n_l + edge_id``) and ``m_{l+1} = 4 m_l`` faces. The new positions
are ``V_{l+1} = S_l V_l`` with ``S_l`` a sparse ``(n_{l+1}, n_l)`` matrix whose rows sum to 1;
the product ``P = S_{L-1} ... S_0`` maps the coarse surface to the fine one (and serves later
as a multigrid prolongation). Each face ``(a, b, c)`` with edge vertices ``ab, bc, ca`` becomes
``(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)``, so the orientation is preserved.

Loop (C. Loop 1987, "Smooth subdivision surfaces based on triangles", MSc thesis, Utah):
  * interior edge ``(a, b)`` with opposite vertices ``c, d``: ``3/8 (a + b) + 1/8 (c + d)``;
  * interior vertex of valence ``k``: ``(1 - k beta) v + beta sum(neighbours)`` with
    Loop's ``beta = (5/8 - (3/8 + 1/4 cos(2 pi / k))^2) / k`` or Warren's simplification
    ``beta = 3/16`` for ``k = 3``, ``3/(8k)`` otherwise (J. Warren 1995);
  * open surfaces (Hoppe et al. 1994 boundary rules): boundary edge midpoint ``(a + b) / 2``,
    boundary vertex ``3/4 v + 1/8 (v_prev + v_next)`` with its two boundary neighbours; a
    boundary vertex with more than two boundary neighbours is a corner and stays fixed.
Linear subdivision uses the midpoint rule on every edge and keeps old vertices in place.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from meshes.errors import InputError

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
Scheme = Literal["linear", "loop"]
BetaRule = Literal["warren", "loop"]


@dataclass(frozen=True)
class SubdivisionOptions:
    """How to subdivide the boundary surface into the shell.

    Attributes:
        levels: number of subdivision levels L (each level multiplies the face count by 4).
        scheme: "linear" (1-to-4 midpoint, the shell stays on the coarse surface) or "loop"
            (approximating, smooth limit; vertices move off the coarse surface).
        beta: vertex rule of Loop subdivision: "warren" (3/(8k), 3/16 for k = 3) or "loop"
            (Loop's original (5/8 - (3/8 + cos(2 pi/k)/4)^2)/k).

    """

    levels: int = 1
    scheme: Scheme = "linear"
    beta: BetaRule = "warren"

    def __post_init__(self) -> None:
        if not isinstance(self.levels, int) or self.levels < 0:
            raise InputError(f"SubdivisionOptions.levels: expected an integer >= 0, "
                             f"got {self.levels!r}")
        if self.scheme not in ("linear", "loop"):
            raise InputError(f"SubdivisionOptions.scheme: expected 'linear' or 'loop', "
                             f"got {self.scheme!r}")
        if self.beta not in ("warren", "loop"):
            raise InputError(f"SubdivisionOptions.beta: expected 'warren' or 'loop', "
                             f"got {self.beta!r}")


@dataclass(frozen=True)
class EdgeTopology:
    """Unique edges of a triangle mesh.

    Attributes:
        edges: ``(E, 2)`` int64 vertex pairs, ``edges[:, 0] < edges[:, 1]``, sorted.
        face_edges: ``(m, 3)`` int64 edge id of the local edge ``(f[j], f[(j+1) % 3])``.
        edge_faces: ``(E,)`` int64 number of faces incident to each edge (1 on a boundary).

    """

    edges: IntArray
    face_edges: IntArray
    edge_faces: IntArray


@dataclass(frozen=True)
class Subdivision:
    """Result of L subdivision levels.

    Attributes:
        vertices: ``(n_L, 3)`` fine positions, equal to ``prolongation @ coarse vertices``.
        faces: ``(m_L, 3)`` fine faces (``m_L = 4^L m_0``), orientation of the coarse faces.
        matrices: the per-level CSR matrices ``S_l`` of shape ``(n_{l+1}, n_l)``.
        face_levels: the face arrays of every level, ``face_levels[0]`` the coarse faces.
        n_coarse: number of coarse vertices ``n_0``.

    """

    vertices: FloatArray
    faces: IntArray
    matrices: tuple[sp.csr_matrix, ...]
    face_levels: tuple[IntArray, ...]
    n_coarse: int

    @property
    def prolongation(self) -> sp.csr_matrix:
        """``P = S_{L-1} ... S_0`` (``n_L x n_0``), identity when L = 0."""
        out = sp.identity(self.n_coarse, format="csr")
        for s in self.matrices:
            out = (s @ out).tocsr()
        return out


def edge_topology(faces: IntArray, n_vertices: int) -> EdgeTopology:
    """Find the unique edges of a triangle mesh by sorting integer keys.

    Args:
        faces: ``(m, 3)`` vertex indices.
        n_vertices: number of vertices (the key is ``min * n + max``).

    Returns:
        The ``EdgeTopology``.

    Raises:
        InputError: if an edge has more than two incident faces (non-manifold).

    """
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    lo, hi = half.min(axis=1), half.max(axis=1)
    keys, inverse, counts = np.unique(lo * np.int64(n_vertices) + hi, return_inverse=True,
                                      return_counts=True)
    if counts.size and counts.max() > 2:
        k = int(keys[np.argmax(counts)])
        raise InputError(f"faces: edge ({k // n_vertices}, {k % n_vertices}) has more than "
                         f"two incident faces (non-manifold surface)")
    edges = np.stack([keys // n_vertices, keys % n_vertices], axis=1)
    return EdgeTopology(edges=edges, face_edges=inverse.reshape(-1, 3).astype(np.int64),
                        edge_faces=counts.astype(np.int64))


def refine_faces(faces: IntArray, face_edges: IntArray, n_vertices: int) -> IntArray:
    """Split each face into its 4 children, orientation preserved.

    Args:
        faces: ``(m, 3)`` vertex indices.
        face_edges: ``(m, 3)`` edge ids of ``(f0, f1), (f1, f2), (f2, f0)``.
        n_vertices: number of coarse vertices; edge ``e`` becomes vertex ``n_vertices + e``.

    Returns:
        ``(4 m, 3)`` faces: children ``4 f .. 4 f + 3`` of face ``f``.

    """
    a, b, c = faces.T
    ab, bc, ca = (face_edges + n_vertices).T
    children = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                         np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)], axis=1)
    return children.reshape(-1, 3)


def _coo(rows: IntArray, cols: IntArray, vals: FloatArray, shape: tuple[int, int]
         ) -> sp.csr_matrix:
    """CSR matrix from triplets, duplicates summed, explicit zeros dropped."""
    out = sp.csr_matrix((vals, (rows, cols)), shape=shape)
    out.eliminate_zeros()
    return out


def _midpoint_rows(topo: EdgeTopology, n: int, interior_weight: float) -> tuple[IntArray, ...]:
    """Triplets of the edge-endpoint weights: ``interior_weight`` on 2-face edges, 1/2 else."""
    n_e = topo.edges.shape[0]
    w = np.where(topo.edge_faces == 2, interior_weight, 0.5)
    rows = np.repeat(n + np.arange(n_e), 2)
    return rows, topo.edges.reshape(-1), np.repeat(w, 2)


def linear_matrix(topo: EdgeTopology, n: int) -> sp.csr_matrix:
    """``S`` of one level of 1-to-4 midpoint subdivision: identity on old, 1/2 on edges.

    Args:
        topo: edges of the current mesh.
        n: number of current vertices.

    Returns:
        ``(n + E, n)`` CSR matrix.

    """
    r, c, v = _midpoint_rows(topo, n, 0.5)
    ident = np.arange(n)
    return _coo(np.concatenate([ident, r]), np.concatenate([ident, c]),
                np.concatenate([np.ones(n), v]), (n + topo.edges.shape[0], n))


def loop_beta(valence: IntArray, rule: BetaRule) -> FloatArray:
    """Loop's vertex weight ``beta(k)`` (Loop 1987 or Warren 1995).

    Args:
        valence: number of neighbours ``k`` per vertex (>= 1).
        rule: "loop" or "warren".

    Returns:
        ``beta`` per vertex.

    """
    k = np.maximum(valence, 1).astype(np.float64)
    if rule == "loop":
        return (5.0 / 8.0 - (3.0 / 8.0 + 0.25 * np.cos(2.0 * np.pi / k)) ** 2) / k
    return np.where(k == 3, 3.0 / 16.0, 3.0 / (8.0 * k))


def _loop_vertex_rows(topo: EdgeTopology, n: int, rule: BetaRule) -> tuple[IntArray, ...]:
    """Triplets of the Loop vertex rules (interior, boundary, corner) for old vertices."""
    e = topo.edges
    bnd = topo.edge_faces == 1
    valence = np.bincount(e.reshape(-1), minlength=n)
    bval = np.bincount(e[bnd].reshape(-1), minlength=n)
    beta = loop_beta(valence, rule)
    # neighbour weight: beta (interior), 1/8 along boundary edges (boundary), 0 (corner)
    both = np.concatenate([e, e[:, ::-1]])
    is_b = np.concatenate([bnd, bnd])
    centre, nbr = both[:, 0], both[:, 1]
    w = np.where(bval[centre] == 0, beta[centre],
                 np.where((bval[centre] == 2) & is_b, 1.0 / 8.0, 0.0))
    self_w = np.where(bval == 0, 1.0 - valence * beta, np.where(bval == 2, 0.75, 1.0))
    ident = np.arange(n)
    return (np.concatenate([ident, centre]), np.concatenate([ident, nbr]),
            np.concatenate([self_w, w]))


def _loop_opposite_rows(faces: IntArray, topo: EdgeTopology, n: int) -> tuple[IntArray, ...]:
    """Triplets of the 1/8 weights of the vertices opposite interior edges."""
    opposite = np.roll(faces, -2, axis=1).reshape(-1)  # local edge j is opposite f[(j+2)%3]
    edge = topo.face_edges.reshape(-1)
    keep = topo.edge_faces[edge] == 2
    return n + edge[keep], opposite[keep], np.full(int(keep.sum()), 1.0 / 8.0)


def loop_matrix(faces: IntArray, topo: EdgeTopology, n: int, rule: BetaRule) -> sp.csr_matrix:
    """``S`` of one level of Loop subdivision with boundary rules.

    Args:
        faces: ``(m, 3)`` current faces.
        topo: their edges.
        n: number of current vertices.
        rule: vertex weight rule, see ``loop_beta``.

    Returns:
        ``(n + E, n)`` CSR matrix with rows summing to 1.

    """
    parts = [_loop_vertex_rows(topo, n, rule), _midpoint_rows(topo, n, 3.0 / 8.0),
             _loop_opposite_rows(faces, topo, n)]
    rows, cols, vals = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return _coo(rows, cols, vals, (n + topo.edges.shape[0], n))


def subdivide_once(faces: IntArray, n: int, scheme: Scheme = "linear",
                   beta: BetaRule = "warren") -> tuple[sp.csr_matrix, IntArray]:
    """One subdivision level.

    Args:
        faces: ``(m, 3)`` vertex indices.
        n: number of vertices.
        scheme: "linear" or "loop".
        beta: Loop vertex rule.

    Returns:
        ``(S, new_faces)`` with ``S`` of shape ``(n + E, n)`` and ``new_faces`` ``(4 m, 3)``.

    """
    topo = edge_topology(faces, n)
    s = linear_matrix(topo, n) if scheme == "linear" else loop_matrix(faces, topo, n, beta)
    return s, refine_faces(faces, topo.face_edges, n)


def subdivide(vertices: FloatArray, faces: IntArray,
              options: SubdivisionOptions | None = None) -> Subdivision:
    """L levels of subdivision, ``V_{l+1} = S_l V_l``.

    Args:
        vertices: ``(n, 3)`` coarse positions.
        faces: ``(m, 3)`` coarse faces (unreferenced vertices are allowed and kept).
        options: levels, scheme and Loop rule (defaults: one linear level).

    Returns:
        The ``Subdivision`` with fine vertices, faces and the per-level matrices.

    Raises:
        InputError: malformed arrays or a non-manifold edge.

    """
    opts = options or SubdivisionOptions()
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces: expected (m, 3) faces and (n, d) vertices, got {f.shape}, "
                         f"{v.shape}")
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise InputError("faces: vertex index out of range")
    n0 = v.shape[0]
    mats, levels = [], [f]
    for _ in range(opts.levels):
        s, f = subdivide_once(f, v.shape[0], opts.scheme, opts.beta)
        v = s @ v
        mats.append(s)
        levels.append(f)
    return Subdivision(vertices=v, faces=f, matrices=tuple(mats), face_levels=tuple(levels),
                       n_coarse=n0)
