"""The tetrahedral mesh container and its pure-numpy derived quantities.

A :class:`TetMesh` holds the coarse body ``Q`` of the embedded-shell method (Rémillard & Kry
2013): vertex positions ``points`` (n, 3) float64 in metres and connectivity ``tets`` (m, 4)
int64. Everything derived from it (signed volumes, the outward boundary surface the shell is
built from, the bounding box, connected components) is a pure function of the two arrays,
computed on demand and cached on the instance.

Orientation convention: a tet ``(v0, v1, v2, v3)`` is positively oriented when
``det[v1 - v0, v2 - v0, v3 - v0] > 0``; its four faces listed in :data:`TET_FACES`
(``(1,2,3), (0,3,2), (0,1,3), (0,2,1)``) then have right-hand normals pointing out of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _cc

from meshes.errors import InputError

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Local vertex triples of the faces of a positively oriented tet, opposite vertex 0..3,
#: ordered so that the right-hand normal points out of the tet.
TET_FACES: IntArray = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


def _frozen_copy(arr: np.ndarray, dtype: type) -> np.ndarray:
    """Return a read-only C-contiguous copy of ``arr`` as ``dtype``.

    An array that already is one (owning its data, read-only, contiguous, of ``dtype``)
    is returned as is, so re-wrapping a mesh's arrays copies nothing.
    """
    if (arr.dtype == dtype and arr.base is None and not arr.flags.writeable
            and arr.flags.c_contiguous):
        return arr
    out: np.ndarray = np.array(arr, dtype=dtype, order="C", copy=True)
    out.setflags(write=False)
    return out


def as_points(points: object, source: str = "<arrays>") -> FloatArray:
    """Copy ``points`` into a read-only C-contiguous (n, 3) float64 array.

    Args:
        points: Anything numpy can convert to a real (n, 3) array.
        source: File or builder name used in error messages.

    Returns:
        The coordinates as float64.

    Raises:
        InputError: Not convertible, complex, or not of shape (n, 3).

    """
    try:
        raw = np.asarray(points)
        if np.iscomplexobj(raw):
            raise InputError(f"{source}: points must be real, got dtype {raw.dtype}")
        arr = _frozen_copy(raw, np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{source}: points are not a numeric array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{source}: points must have shape (n, 3), got {arr.shape}")
    return arr


def as_tets(tets: object, n_points: int, source: str = "<arrays>") -> IntArray:
    """Copy ``tets`` into a read-only (m, 4) int64 array of indices in ``[0, n_points)``.

    Args:
        tets: Anything numpy can convert to an integer (m, 4) array.
        n_points: Number of vertices the indices refer to.
        source: File or builder name used in error messages.

    Returns:
        The connectivity as int64.

    Raises:
        InputError: Non-integer dtype, wrong shape, empty, or an index out of range
            (the message names the first offending tet).

    """
    try:
        raw = np.asarray(tets)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{source}: tets are not an array ({exc})") from None
    if raw.dtype.kind not in "iu":
        raise InputError(f"{source}: tets must be integer vertex indices, got dtype {raw.dtype}")
    if raw.ndim != 2 or raw.shape[1] != 4:
        raise InputError(f"{source}: tets must have shape (m, 4), got {raw.shape}")
    if raw.shape[0] == 0 or n_points == 0:
        raise InputError(f"{source}: empty mesh ({n_points} points, {raw.shape[0]} tets)")
    bad = np.flatnonzero(((raw < 0) | (raw >= n_points)).any(axis=1))
    if bad.size:
        i = int(bad[0])
        raise InputError(f"{source}: tet {i} has a vertex index out of range [0, {n_points}): "
                         f"{raw[i].tolist()} ({bad.size} such tets)")
    return _frozen_copy(raw, np.int64)


def tet_volumes(points: FloatArray, tets: IntArray) -> FloatArray:
    """Signed volumes ``V = det[p1 - p0, p2 - p0, p3 - p0] / 6`` of every tet.

    Args:
        points: (n, 3) vertex positions.
        tets: (m, 4) vertex indices.

    Returns:
        (m,) signed volumes, positive for positively oriented tets.

    """
    p = points[tets]
    d = p[:, 1:, :] - p[:, :1, :]
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def max_edge_lengths(points: FloatArray, tets: IntArray) -> FloatArray:
    """Longest of the six edge lengths of every tet.

    Args:
        points: (n, 3) vertex positions.
        tets: (m, 4) vertex indices.

    Returns:
        (m,) longest edge length per tet.

    """
    p = points[tets]
    i, j = np.triu_indices(4, k=1)
    return np.linalg.norm(p[:, i, :] - p[:, j, :], axis=2).max(axis=1)


def group_rows(rows: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Group equal rows of an integer array, like ``np.unique(rows, axis=0)`` but faster.

    Rows are packed into one int64 key ``sum_c (r_c - min) span^(k-1-c)`` when that fits
    (a 1-D sort instead of a lexicographic one); otherwise ``np.unique(axis=0)`` is used.

    Args:
        rows: (k, c) integer array.

    Returns:
        ``(first, inverse, counts)``: index of the first row of each group (groups in
        sorted order), the group of every row (k,), and the size of every group.

    """
    rows = np.asarray(rows, dtype=np.int64)
    if rows.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty
    low = int(rows.min())
    span = int(rows.max()) - low + 1
    if span ** rows.shape[1] < 2**62:
        key = np.zeros(rows.shape[0], dtype=np.int64)
        for col in range(rows.shape[1]):
            key = key * span + (rows[:, col] - low)
        _, first, inverse, counts = np.unique(key, return_index=True, return_inverse=True,
                                              return_counts=True)
    else:
        _, first, inverse, counts = np.unique(rows, axis=0, return_index=True,
                                              return_inverse=True, return_counts=True)
    return first.astype(np.int64), inverse.reshape(-1).astype(np.int64), counts.astype(np.int64)


def face_keys(faces: IntArray) -> tuple[IntArray, IntArray]:
    """Group faces by vertex set (orientation ignored).

    Args:
        faces: (k, 3) vertex triples.

    Returns:
        ``(inverse, counts)``: the group of every face and the size of every group.

    """
    _, inverse, counts = group_rows(np.sort(faces, axis=1))
    return inverse, counts


def boundary_faces_with_cells(tets: IntArray) -> tuple[IntArray, IntArray]:
    """Boundary faces of a tet mesh and the tet each one belongs to.

    A face is on the boundary when exactly one tet has it. With positively oriented tets
    (see :func:`tet_volumes`) the returned triangles are oriented outward, i.e. the
    right-hand normal ``(b - a) x (c - a)`` of ``(a, b, c)`` points out of the body.

    Args:
        tets: (m, 4) vertex indices of positively oriented tets.

    Returns:
        ``(faces, cells)``: (k, 3) outward triangles and (k,) index of the owning tet,
        in order of tet index then local face.

    """
    all_faces = tets[:, TET_FACES].reshape(-1, 3)
    inverse, counts = face_keys(all_faces)
    once = np.flatnonzero(counts[inverse] == 1)
    return np.ascontiguousarray(all_faces[once]), once // 4


def boundary_triangles(tets: IntArray) -> IntArray:
    """Outward-oriented boundary triangles of a tet mesh (pure numpy).

    This is the surface the embedded shell is built from (Rémillard & Kry 2013, Algorithm 1:
    extract the boundary of Q, then subdivide).

    Args:
        tets: (m, 4) vertex indices of positively oriented tets.

    Returns:
        (k, 3) triangles whose right-hand normals point out of the body.

    """
    return boundary_faces_with_cells(tets)[0]


def boundary_surface(tets: IntArray) -> tuple[IntArray, IntArray]:
    """Boundary as a standalone triangle mesh with its map to the coarse nodes.

    Args:
        tets: (m, 4) vertex indices of positively oriented tets.

    Returns:
        ``(nodes, faces)``: ``nodes`` (s,) sorted coarse vertex ids on the boundary, and
        ``faces`` (k, 3) outward triangles indexing into ``nodes`` (so the surface positions
        are ``points[nodes]``).

    """
    tris = boundary_triangles(tets)
    nodes, local = np.unique(tris, return_inverse=True)
    return nodes.astype(np.int64), local.reshape(-1, 3).astype(np.int64)


def tet_components(tets: IntArray) -> tuple[int, IntArray]:
    """Label the connected components of tets that share a face.

    Args:
        tets: (m, 4) vertex indices.

    Returns:
        ``(count, labels)`` with ``labels`` (m,) the component of each tet.

    """
    m = tets.shape[0]
    inverse, _ = face_keys(tets[:, TET_FACES].reshape(-1, 3))
    owner = np.repeat(np.arange(m), 4)
    graph = sp.coo_matrix((np.ones(owner.size), (owner, inverse)), shape=(m, inverse.max() + 1))
    adjacency = graph.tocsr() @ graph.T.tocsr()
    count, labels = _cc(adjacency, directed=False)
    return int(count), labels.astype(np.int64)


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A linear tetrahedral mesh as plain numpy arrays (no dolfinx).

    Construction coerces and checks shapes, dtypes and index ranges only (raising
    ``InputError``); geometric checks (finite coordinates, positive volumes, no duplicates,
    closed manifold boundary) are done by :func:`meshes.validate.validate`, which every
    builder and the loader apply. The arrays are made read-only.

    Attributes:
        points: (n, 3) float64 vertex positions in metres.
        tets: (m, 4) int64 vertex indices, positively oriented after validation.
        source: Where the mesh came from: a file path, or a builder name with its
            parameters (e.g. ``"box(lx=1.0, ly=1.0, lz=1.0, h=0.5, origin=(0, 0, 0))"``).

    """

    points: FloatArray
    tets: IntArray
    source: str = field(default="<arrays>")

    def __post_init__(self) -> None:
        if not isinstance(self.source, str):
            raise InputError(f"TetMesh.source must be a string, got {type(self.source).__name__}")
        points = as_points(self.points, self.source)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tets", as_tets(self.tets, points.shape[0], self.source))

    def __repr__(self) -> str:
        return f"TetMesh(n_points={self.n_points}, n_tets={self.n_tets}, source={self.source!r})"

    @property
    def n_points(self) -> int:
        """Number of vertices ``n``."""
        return int(self.points.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tets ``m``."""
        return int(self.tets.shape[0])

    @cached_property
    def volumes(self) -> FloatArray:
        """(m,) signed tet volumes (see :func:`tet_volumes`)."""
        return tet_volumes(self.points, self.tets)

    @property
    def volume(self) -> float:
        """Total volume ``sum_t V_t``."""
        return float(self.volumes.sum())

    @cached_property
    def boundary(self) -> IntArray:
        """(k, 3) outward boundary triangles (see :func:`boundary_triangles`)."""
        return boundary_triangles(self.tets)

    @cached_property
    def bbox(self) -> tuple[FloatArray, FloatArray]:
        """Axis-aligned bounding box ``(lower corner, upper corner)``."""
        return self.points.min(axis=0), self.points.max(axis=0)

    @cached_property
    def mean_edge_length(self) -> float:
        """Mean length of the distinct edges, a characteristic size ``h``."""
        i, j = np.triu_indices(4, k=1)
        pairs = np.sort(np.stack([self.tets[:, i], self.tets[:, j]], axis=2).reshape(-1, 2),
                        axis=1)
        edges = pairs[group_rows(pairs)[0]]
        return float(np.linalg.norm(self.points[edges[:, 0]] - self.points[edges[:, 1]],
                                    axis=1).mean())

    @cached_property
    def n_components(self) -> int:
        """Number of face-connected components (see :func:`tet_components`)."""
        return tet_components(self.tets)[0]
