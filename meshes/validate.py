"""Validation of tetrahedral meshes from any source (builders, files, raw arrays).

Every check raises :class:`meshes.errors.InputError` with a one-line message naming the
mesh source (file path or builder) and the offending element, point, face, edge or vertex.
On arbitrary garbage input (wrong shapes, negative, out-of-range or float indices, NaN)
:func:`validate` raises nothing but ``InputError``.

Checks, in order:

1. structure: ``points`` (n, 3) real, ``tets`` (m, 4) integer in ``[0, n)``, non-empty;
2. coordinates: finite and ``|x| <= max_abs_coordinate``;
3. unreferenced points dropped (optional);
4. no degenerate tet: ``|V_t| > degenerate_tol * l_t^3`` with ``l_t`` the tet's longest edge
   (scale invariant; a regular tet has ``V / l^3 = 1 / (6 sqrt 2) ~ 0.118``);
5. positive orientation ``V_t > 0``; inverted tets are re-oriented (swap of two vertices)
   with a :class:`MeshWarning` when ``fix_orientation`` is set, refused otherwise;
6. no duplicate tets (same vertex set) and no two tets on the same side of a face;
7. every face shared by at most two tets;
8. closed, edge-manifold boundary: each boundary edge in exactly two boundary triangles;
9. vertex-manifold boundary: the boundary triangles around each boundary vertex form a single
   fan (two cubes touching at one corner are refused).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from meshes.errors import InputError
from meshes.tetmesh import (
    TET_FACES,
    FloatArray,
    IntArray,
    TetMesh,
    as_points,
    as_tets,
    boundary_faces_with_cells,
    face_keys,
    group_rows,
    max_edge_lengths,
    tet_volumes,
)


class MeshWarning(UserWarning):
    """A mesh was accepted after a repair (e.g. inverted tets re-oriented)."""


@dataclass(frozen=True)
class ValidationOptions:
    """Tolerances and repairs applied by :func:`validate`.

    Attributes:
        fix_orientation: Re-orient inverted tets (negative volume) by swapping their last
            two vertices, with a ``MeshWarning``; if False they are refused.
        degenerate_tol: A tet is degenerate when ``|V| <= degenerate_tol * l_max^3``
            (``l_max`` its longest edge, dimensionless tolerance).
        max_abs_coordinate: Largest accepted ``|coordinate|`` in metres; larger values are
            refused as absurd (unit mistakes, garbage).
        drop_unreferenced: Remove points no tet uses (renumbering the others) instead of
            keeping them.
        check_manifold: Require a closed manifold boundary (edge and vertex manifold).

    """

    fix_orientation: bool = True
    degenerate_tol: float = 1e-8
    max_abs_coordinate: float = 1e8
    drop_unreferenced: bool = True
    check_manifold: bool = True

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            ok = (isinstance(value, bool) if f.type == "bool" else
                  isinstance(value, int | float) and not isinstance(value, bool))
            if not ok:
                raise InputError(f"ValidationOptions.{f.name} must be a {f.type}, got {value!r}")
        if not (math.isfinite(self.degenerate_tol) and 0.0 <= self.degenerate_tol < 0.1):
            raise InputError(f"ValidationOptions.degenerate_tol must be in [0, 0.1), "
                             f"got {self.degenerate_tol}")
        if not (math.isfinite(self.max_abs_coordinate) and self.max_abs_coordinate > 0):
            raise InputError(f"ValidationOptions.max_abs_coordinate must be finite and > 0, "
                             f"got {self.max_abs_coordinate}")


def resolve_options(options: ValidationOptions | None,
                    overrides: Mapping[str, Any]) -> ValidationOptions:
    """Return ``options`` (default ``ValidationOptions()``) with fields replaced by overrides.

    Raises:
        InputError: An override names no field of :class:`ValidationOptions`.

    """
    base = ValidationOptions() if options is None else options
    unknown = sorted(set(overrides) - {f.name for f in fields(ValidationOptions)})
    if unknown:
        raise InputError(f"ValidationOptions has no field {unknown[0]!r}")
    return replace(base, **overrides)


def _user_of(tets: IntArray, point: int) -> str:
    """Describe the first tet using ``point`` (for messages)."""
    users = np.flatnonzero((tets == point).any(axis=1))
    return f"used by tet {int(users[0])}" if users.size else "used by no tet"


def check_coordinates(points: FloatArray, tets: IntArray, source: str,
                      options: ValidationOptions) -> None:
    """Refuse non-finite or absurdly large coordinates of the points that will be kept.

    Raises:
        InputError: Naming the first bad point and a tet that uses it.

    """
    keep = np.zeros(points.shape[0], dtype=bool)
    keep[tets.reshape(-1)] = True
    if not options.drop_unreferenced:
        keep[:] = True
    with np.errstate(invalid="ignore"):
        bad_nan = keep & ~np.isfinite(points).all(axis=1)
        bad_big = keep & (np.abs(points) > options.max_abs_coordinate).any(axis=1)
    for bad, what in ((bad_nan, "a non-finite coordinate"),
                      (bad_big, f"a coordinate beyond +-{options.max_abs_coordinate:g} m")):
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"{source}: point {i} ({_user_of(tets, i)}) has {what}: "
                             f"{points[i].tolist()}")


def drop_unreferenced(points: FloatArray, tets: IntArray) -> tuple[FloatArray, IntArray]:
    """Remove points no tet references and renumber the tets accordingly.

    Returns:
        ``(points, tets)`` compacted (unchanged arrays when every point is used).

    """
    used = np.unique(tets)
    if used.size == points.shape[0]:
        return points, tets
    remap = np.full(points.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return points[used], remap[tets]


def check_degenerate(points: FloatArray, tets: IntArray, volumes: FloatArray, source: str,
                     tol: float) -> None:
    """Refuse tets with ``|V| <= tol * l_max^3`` (including repeated vertices).

    Raises:
        InputError: Naming the first degenerate tet, its volume and vertices.

    """
    with np.errstate(over="ignore", invalid="ignore"):
        scale = max_edge_lengths(points, tets) ** 3
        bad = ~(np.abs(volumes) > tol * scale)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{source}: tet {i} is degenerate: volume {volumes[i]:.3e} <= "
                         f"{tol:g} * l_max^3 = {tol * scale[i]:.3e} (vertices "
                         f"{tets[i].tolist()}; {int(bad.sum())} degenerate tets)")


def orient(tets: IntArray, volumes: FloatArray, source: str, fix: bool) -> IntArray:
    """Return ``tets`` with every inverted tet (``V < 0``) re-oriented or refuse them.

    Swapping vertices 2 and 3 flips the sign of ``det[p1 - p0, p2 - p0, p3 - p0]``.

    Raises:
        InputError: When ``fix`` is False, naming the first inverted tet.

    """
    neg = np.flatnonzero(volumes < 0)
    if neg.size == 0:
        return tets
    i = int(neg[0])
    if not fix:
        raise InputError(f"{source}: tet {i} is inverted (volume {volumes[i]:.3e} < 0, "
                         f"{neg.size} inverted tets; fix_orientation is off)")
    warnings.warn(f"{source}: re-oriented {neg.size} inverted tets (first: tet {i})",
                  MeshWarning, stacklevel=3)
    fixed = tets.copy()
    fixed[neg, 2], fixed[neg, 3] = tets[neg, 3], tets[neg, 2]
    return fixed


def _first_duplicate_pair(keys: IntArray) -> tuple[int, int] | None:
    """First two row indices with equal rows of ``keys``, or None."""
    _, inverse, counts = group_rows(keys)
    dup = np.flatnonzero(counts[inverse] > 1)
    if dup.size == 0:
        return None
    first = int(dup[0])
    second = int(np.flatnonzero(inverse == inverse[first])[1])
    return first, second


def check_duplicates(tets: IntArray, source: str) -> None:
    """Refuse two tets with the same vertex set.

    Raises:
        InputError: Naming both tet indices.

    """
    pair = _first_duplicate_pair(np.sort(tets, axis=1))
    if pair is not None:
        i, j = pair
        raise InputError(f"{source}: tets {i} and {j} are duplicates (vertices "
                         f"{sorted(tets[i].tolist())})")


def _cyclic_canonical(faces: IntArray) -> IntArray:
    """Rotate each oriented triangle so its smallest vertex comes first (keeps orientation)."""
    shift = np.argmin(faces, axis=1)
    cols = (shift[:, None] + np.arange(3)[None, :]) % 3
    return np.take_along_axis(faces, cols, axis=1)


def check_faces(tets: IntArray, source: str) -> None:
    """Refuse faces shared by more than two tets, or by two tets on the same side.

    With positive orientation the two tets of an interior face list it in opposite
    directions; the same direction means the tets overlap.

    Raises:
        InputError: Naming the face's vertices and the tets involved.

    """
    faces = tets[:, TET_FACES].reshape(-1, 3)
    inverse, counts = face_keys(faces)
    over = np.flatnonzero(counts[inverse] > 2)
    if over.size:
        owners = np.flatnonzero(inverse == inverse[over[0]]) // 4
        raise InputError(f"{source}: face {sorted(faces[over[0]].tolist())} is shared by "
                         f"{owners.size} tets {owners.tolist()} (non-manifold)")
    pair = _first_duplicate_pair(_cyclic_canonical(faces))
    if pair is not None:
        i, j = pair[0] // 4, pair[1] // 4
        raise InputError(f"{source}: tets {i} and {j} overlap across face "
                         f"{sorted(faces[pair[0]].tolist())}")


def _half_edges(tris: IntArray) -> tuple[IntArray, IntArray]:
    """Directed edges ``(a -> b)`` of the triangles (3k, 2) and their start corners (3k,)."""
    start = tris.reshape(-1)
    end = np.roll(tris, -1, axis=1).reshape(-1)
    return np.stack([start, end], axis=1), np.arange(start.size)


def check_boundary_edges(tris: IntArray, cells: IntArray, source: str) -> None:
    """Require every boundary edge to lie in exactly two boundary triangles.

    Raises:
        InputError: Naming the edge's vertices, its triangle count and owning tets.

    """
    if tris.shape[0] == 0:
        raise InputError(f"{source}: the mesh has no boundary faces (not a closed body)")
    half, _ = _half_edges(tris)
    _, inverse, counts = group_rows(np.sort(half, axis=1))
    bad = np.flatnonzero(counts[inverse] != 2)
    if bad.size:
        h = int(bad[0])
        owners = np.unique(cells[np.flatnonzero(inverse == inverse[h]) // 3])
        raise InputError(f"{source}: boundary edge {sorted(half[h].tolist())} is in "
                         f"{int(counts[inverse[h]])} boundary triangles (tets "
                         f"{owners.tolist()}), expected 2: boundary not a closed manifold")


def check_boundary_vertices(tris: IntArray, source: str) -> None:
    """Require the boundary triangles around each vertex to form a single fan.

    Corners ``(triangle, vertex)`` are linked across each boundary edge (shared by exactly
    two triangles, see :func:`check_boundary_edges`); a vertex whose corners fall in more
    than one connected component is a pinch point (vertex non-manifold).

    Raises:
        InputError: Naming the vertex and its number of fans.

    """
    half, corner = _half_edges(tris)
    end_corner = 3 * (corner // 3) + (corner % 3 + 1) % 3
    order = np.lexsort((half.max(axis=1), half.min(axis=1)))
    h1, h2 = order[0::2], order[1::2]
    same = half[h1, 0] == half[h2, 0]
    links = np.concatenate([
        np.stack([corner[h1], np.where(same, corner[h2], end_corner[h2])], axis=1),
        np.stack([end_corner[h1], np.where(same, end_corner[h2], corner[h2])], axis=1)])
    n = corner.size
    graph = sp.coo_matrix((np.ones(links.shape[0]), (links[:, 0], links[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    corner_vertex = tris.reshape(-1)
    first, _, _ = group_rows(np.stack([corner_vertex, label], axis=1))
    nfans = np.bincount(corner_vertex[first])
    bad = np.flatnonzero(nfans > 1)
    if bad.size:
        v = int(bad[0])
        raise InputError(f"{source}: boundary vertex {v} joins {int(nfans[v])} separate "
                         f"surface fans (vertex non-manifold, e.g. bodies touching at a point)")


def _coerce(mesh: TetMesh | object, tets: object, source: str | None) -> TetMesh:
    if isinstance(mesh, TetMesh):
        if tets is not None:
            raise InputError(f"{mesh.source}: pass either a TetMesh or (points, tets)")
        return mesh if source is None else TetMesh(mesh.points, mesh.tets, source)
    src = "<arrays>" if source is None else source
    points = as_points(mesh, src)
    if tets is None:
        raise InputError(f"{src}: tets are missing")
    return TetMesh(points, as_tets(tets, points.shape[0], src), src)


def validate(mesh: TetMesh | object, tets: object = None, *, source: str | None = None,
             options: ValidationOptions | None = None, **overrides: bool | float) -> TetMesh:
    """Check a tet mesh and return a clean, positively oriented copy.

    Usable on builder output (``validate(mesh)``) and on raw arrays
    (``validate(points, tets, source="my.vtu")``). See the module docstring for the list
    of checks.

    Args:
        mesh: A :class:`TetMesh`, or the (n, 3) points when ``tets`` is given.
        tets: (m, 4) vertex indices when ``mesh`` is an array of points.
        source: Name used in messages (defaults to ``mesh.source`` or ``"<arrays>"``).
        options: Tolerances and repairs; defaults to ``ValidationOptions()``.
        **overrides: Fields of ``options`` to replace, e.g. ``fix_orientation=False``.

    Returns:
        A :class:`TetMesh` with finite coordinates, positive non-degenerate tets, no
        unreferenced points (if ``drop_unreferenced``) and a closed manifold boundary.

    Raises:
        InputError: The first failed check, naming the source and the element.

    """
    opts = resolve_options(options, overrides)
    m = _coerce(mesh, tets, source)
    src = m.source
    check_coordinates(m.points, m.tets, src, opts)
    points, cells = (drop_unreferenced(m.points, m.tets) if opts.drop_unreferenced
                     else (m.points, m.tets))
    volumes = tet_volumes(points, cells)
    check_degenerate(points, cells, volumes, src, opts.degenerate_tol)
    cells = orient(cells, volumes, src, opts.fix_orientation)
    check_duplicates(cells, src)
    check_faces(cells, src)
    if opts.check_manifold:
        tris, owners = boundary_faces_with_cells(cells)
        check_boundary_edges(tris, owners, src)
        check_boundary_vertices(tris, src)
    if points is m.points and cells is m.tets:
        return m
    return TetMesh(points, cells, src)

