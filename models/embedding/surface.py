"""Outward-oriented boundary surface of a tetrahedral mesh (pure numpy).

A face of a tetrahedron lies on the boundary when no other tetrahedron shares it
(``meshes.tetmesh.boundary_faces_with_cells``). Because a dolfinx mesh does not guarantee
positively oriented cells, each face is then oriented geometrically: its right-hand normal
``(x1 - x0) x (x2 - x0)`` points away from the fourth vertex of the owning tetrahedron
(Grinspun et al. 2003 and Remillard & Kry 2013 embed a shell made of exactly these faces,
refined by subdivision).

The surface vertices are the boundary nodes sorted by their node index, and the faces are
rotated to start at their smallest vertex and sorted lexicographically, so the result depends
only on the node indices and coordinates, not on the order of the tetrahedra: a mesh gathered
from any number of MPI ranks with input (file) node numbering gives the identical surface
(``models.embedding.embedding.mesh_surface`` does that gathering for a dolfinx mesh).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from meshes.errors import InputError
from meshes.tetmesh import boundary_faces_with_cells

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class Surface:
    """A triangle mesh with its map to the nodes of the coarse mesh it came from.

    Attributes:
        vertices: ``(n, 3)`` float64 positions of the surface vertices.
        faces: ``(m, 3)`` int64 vertex indices, counter-clockwise seen from outside
            (right-hand normal points out of the body).
        node_map: ``(n,)`` int64 index of each surface vertex in the coarse mesh's node array
            (for a dolfinx mesh: the input/global node index, see ``mesh_surface``).

    """

    vertices: FloatArray
    faces: IntArray
    node_map: IntArray

    def __post_init__(self) -> None:
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise InputError(f"Surface.vertices: expected shape (n, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise InputError(f"Surface.faces: expected shape (m, 3), got {self.faces.shape}")
        if self.node_map.shape != (self.vertices.shape[0],):
            raise InputError("Surface.node_map: expected one entry per vertex")


def _validate_tets(points: FloatArray, tets: IntArray) -> None:
    """Raise InputError for malformed ``points`` / ``tets`` arrays."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points: expected shape (n, 3), got {points.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise InputError(f"tets: expected shape (m, 4), got {tets.shape}")
    if tets.size and (tets.min() < 0 or tets.max() >= points.shape[0]):
        raise InputError("tets: node index out of range of points")


def canonical_faces(faces: IntArray) -> IntArray:
    """Rotate each triangle cyclically so its smallest index comes first, then sort the rows.

    Cyclic rotation keeps the orientation; the result depends only on the set of oriented
    triangles, not on their order or starting vertex.

    Args:
        faces: ``(k, 3)`` vertex triples.

    Returns:
        ``(k, 3)`` canonical, lexicographically sorted triples.

    """
    shift = np.argmin(faces, axis=1)
    cols = (shift[:, None] + np.arange(3)[None, :]) % 3
    rot = np.take_along_axis(faces, cols, axis=1)
    return rot[np.lexsort(rot.T[::-1])]


def orient_outward(points: FloatArray, tets: IntArray, faces: IntArray,
                   owner: IntArray) -> IntArray:
    """Flip faces whose right-hand normal points towards the owning tet's opposite vertex.

    A face ``(a, b, c)`` of tetrahedron ``t`` with opposite vertex ``d`` points outward when
    ``((b - a) x (c - a)) . (d - a) < 0``.

    Args:
        points: ``(n, 3)`` node positions.
        tets: ``(m, 4)`` node indices.
        faces: ``(k, 3)`` boundary faces.
        owner: ``(k,)`` owning tetrahedron of each face.

    Returns:
        ``(k, 3)`` faces with outward orientation.

    Raises:
        InputError: if a boundary tetrahedron is degenerate (zero volume).

    """
    t = tets[owner]
    opposite = t.sum(axis=1) - faces.sum(axis=1)
    a, b, c = (points[faces[:, j]] for j in range(3))
    side = np.einsum("ij,ij->i", np.cross(b - a, c - a), points[opposite] - a)
    if np.any(side == 0.0):
        raise InputError(f"tets: element {int(owner[np.argmax(side == 0.0)])} is degenerate")
    out = faces.copy()
    flip = side > 0.0
    out[flip] = out[flip][:, [0, 2, 1]]
    return out


def boundary_surface(points: FloatArray, tets: IntArray) -> Surface:
    """Outward-oriented boundary triangle mesh of a tetrahedral mesh.

    Args:
        points: ``(n, 3)`` node positions (the P1 geometry).
        tets: ``(m, 4)`` node indices.

    Returns:
        The boundary ``Surface``: vertices are the boundary nodes sorted by node index,
        ``node_map`` holds those node indices.

    Raises:
        InputError: malformed arrays or a degenerate boundary element.

    """
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    _validate_tets(points, tets)
    faces, owner = boundary_faces_with_cells(tets)
    faces = canonical_faces(orient_outward(points, tets, faces, owner))
    nodes, local = np.unique(faces, return_inverse=True)
    return Surface(vertices=points[nodes].copy(), faces=local.reshape(-1, 3).astype(np.int64),
                   node_map=nodes.astype(np.int64))


def signed_volume(vertices: FloatArray, faces: IntArray) -> float:
    """Volume enclosed by a closed triangle mesh, positive for outward orientation.

    ``V = (1/6) sum_f x_a . (x_b x x_c)`` (divergence theorem).

    Args:
        vertices: ``(n, 3)`` positions.
        faces: ``(m, 3)`` vertex indices.

    Returns:
        The signed volume.

    """
    a, b, c = (vertices[faces[:, j]] for j in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)
