"""Cap slivers of the shell's coarse surface removed by edge flips (pure numpy).

A *cap* is a triangle ``(a, b, c)`` whose apex ``c`` lies at a small height ``h`` over its
longest edge ``ab`` (one angle near 180 degrees; its quality ``q = 4 sqrt(3) A / sum |e|^2 ~
sqrt(3) h / |ab|``). A tet mesher leaves such faces on a body's boundary (IPC's bunny has ten
below ``q = 0.1``), and subdivision copies them into the shell. The hinge across ``ab`` then
has the weight ``3 |ab|^2 / (A_1 + A_2)`` of a near-zero area and an angle Hessian growing
as ``1 / h^2``: its negative curvature sets the shift of the whole shell's Newton matrix
(docs/notes/sliver-hinges.md).

The flip replaces the cap and its neighbour across the long edge, ``(a, b, c)`` and ``(b, a,
d)``, by ``(a, d, c)`` and ``(d, b, c)`` (Lawson's edge flip): the same vertices, the same
face count and orientation, the quadrilateral ``a d b c`` split by its other diagonal. The
surface moves by at most the cap's height ``h`` (the two triangulations bound the thin
tetrahedron ``a b c d``), a distance the embedding B absorbs (its points may lie off the
body's boundary by a tolerance, :mod:`models.embedding.embedding`). A flip is taken only when

* ``ab`` has exactly one neighbouring face, no edge of the pair is shared by more than two
  faces (a non-manifold edge, e.g. where two tets touch by an edge) and the edge ``cd`` does
  not exist yet (the surface keeps its topology, without duplicate edges),
* the worse of the two new faces is better than the worse of the two old ones, and
* both new faces turn by at most 60 degrees from the pair's area-weighted normal (no fold).

Caps are treated worst first until none below ``max_quality`` can be flipped. The result
depends only on the surface (every rank computes the same), its faces canonical as
:func:`models.embedding.surface.canonical_faces` gives them; a surface without caps is
returned unchanged.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from meshes.report import triangle_quality
from models.embedding.surface import Surface, canonical_faces

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

CAP_QUALITY: float = 0.1
"""Faces below this quality are caps to flip (``h / |ab|`` below about 0.058)."""
MIN_ALIGNMENT: float = 0.5
"""Cosine of the largest turn of a new face from the pair's normal (60 degrees)."""


@dataclass(frozen=True)
class CapFlips:
    """The surface with its caps flipped, and what changed.

    Attributes:
        surface: The new surface (the input one when nothing was flipped).
        flips: Number of edge flips.
        quality_before: Smallest face quality before.
        quality_after: Smallest face quality after.
        moved: Largest height of a flipped cap's apex over its long edge: a bound on how far
            the surface moved (mesh length unit).

    """

    surface: Surface
    flips: int
    quality_before: float
    quality_after: float
    moved: float


def flip_caps(surface: Surface, max_quality: float = CAP_QUALITY) -> CapFlips:
    """Flip the long edge of every cap below ``max_quality`` the module's conditions allow."""
    v, faces = surface.vertices, surface.faces.copy()
    q = triangle_quality(v, faces)
    before = float(q.min()) if q.size else 1.0
    if not before < max_quality:  # no cap: no edge map to build
        return CapFlips(surface, 0, before, before, 0.0)
    edges = [(int(f[k]), int(f[(k + 1) % 3])) for f in faces for k in range(3)]
    counts = Counter(edge for a, b in edges for edge in ((a, b), (b, a)))
    shared = {edge for edge, n in counts.items() if n > 2}  # an edge of more than two faces
    owner = {edge: index // 3 for index, edge in enumerate(edges) if edge not in shared}
    flips, moved = 0, 0.0
    refused: set[int] = set()
    while True:
        caps = [int(i) for i in np.flatnonzero(q < max_quality) if int(i) not in refused]
        if not caps:
            break
        i = min(caps, key=lambda c: (q[c], c))  # the worst cap first
        height = _flip(v, faces, q, owner, i, shared)
        if height is None:
            refused.add(i)
            continue
        flips += 1
        moved = max(moved, height)
        refused.clear()  # a flip changes its neighbours' options
    if flips == 0:
        return CapFlips(surface, 0, before, before, 0.0)
    new = Surface(vertices=v, faces=canonical_faces(faces), node_map=surface.node_map)
    return CapFlips(new, flips, before, float(q.min()), moved)


def _flip(v: FloatArray, faces: IntArray, q: FloatArray, owner: dict[tuple[int, int], int],
          i: int, shared: set[tuple[int, int]]) -> float | None:
    """Flip face ``i``'s longest edge in place if allowed; return the cap's height or None.

    ``shared``: the (directed) edges of more than two faces, which no flip touches.
    """
    f = faces[i]
    lengths = [np.linalg.norm(v[f[(k + 1) % 3]] - v[f[k]]) for k in range(3)]
    k = int(np.argmax(lengths))
    a, b, c = int(f[k]), int(f[(k + 1) % 3]), int(f[(k + 2) % 3])
    j = owner.get((b, a))
    if j is None:
        return None
    d = int(next(x for x in faces[j] if x not in (a, b)))
    pair_edges = {(int(x[m]), int(x[(m + 1) % 3])) for x in (faces[i], faces[j]) for m in range(3)}
    if pair_edges & shared or (c, d) in owner or (d, c) in owner or (c, d) in shared:
        return None
    new = np.array([[a, d, c], [d, b, c]], dtype=faces.dtype)
    q_new = triangle_quality(v, new)
    if q_new.min() <= min(q[i], q[j]):
        return None
    pair = np.cross(v[b] - v[a], v[c] - v[a]) + np.cross(v[a] - v[b], v[d] - v[b])
    normals = np.cross(v[new[:, 1]] - v[new[:, 0]], v[new[:, 2]] - v[new[:, 0]])
    cosines = normals @ pair / (np.linalg.norm(normals, axis=1) * np.linalg.norm(pair))
    if cosines.min() < MIN_ALIGNMENT:
        return None
    for face in (faces[i], faces[j]):
        for m in range(3):
            del owner[(int(face[m]), int(face[(m + 1) % 3]))]
    faces[i], faces[j] = new
    q[i], q[j] = q_new
    for index in (i, j):
        for m in range(3):
            owner[(int(faces[index][m]), int(faces[index][(m + 1) % 3]))] = index
    ab = v[b] - v[a]
    return float(np.linalg.norm(np.cross(ab, v[c] - v[a])) / np.linalg.norm(ab))


__all__ = ["CAP_QUALITY", "CapFlips", "flip_caps"]
