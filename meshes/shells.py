"""Pure-numpy triangle-mesh generators for shell tests and benchmarks.

Every generator returns ``(points, faces)``: ``points`` an ``(n, 3)`` float64 array and
``faces`` an ``(F, 3)`` int64 array, consistently oriented (counter-clockwise seen from +z for
plates, outward normals for the sphere), as required by
:meth:`models.shell.topology.ShellTopology.from_faces`. No gmsh, no dolfinx.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.spatial import Delaunay

from meshes.errors import InputError

Mesh = tuple[np.ndarray, np.ndarray]


def _require_positive(name: str, value: float) -> None:
    """Raise InputError naming ``name`` unless ``value > 0``."""
    if not value > 0:
        raise InputError(f"meshes.shells: {name} must be > 0, got {value!r}")


def _lattice_index(nx: int, ny: int) -> np.ndarray:
    """Vertex index ``v[j, i] = j (nx + 1) + i`` of an ``(ny+1) x (nx+1)`` vertex lattice."""
    return np.arange((nx + 1) * (ny + 1), dtype=np.int64).reshape(ny + 1, nx + 1)


def equilateral_plate(nx: int, ny: int, a: float = 1.0) -> Mesh:
    """Flat plate of equilateral triangles with edge length ``a`` in the plane z = 0.

    Row ``j`` holds ``nx + 1`` vertices at ``x = a (i + (j mod 2)/2)``, ``y = j a sqrt(3)/2``;
    each strip between two rows holds ``2 nx`` equilateral triangles: a rectangle with
    zig-zag left/right sides, ``(nx+1)(ny+1)`` vertices and ``2 nx ny`` faces.

    Args:
        nx: Cells per row (>= 1).
        ny: Rows of cells (>= 1).
        a: Edge length.

    Returns:
        (points, faces), faces counter-clockwise seen from +z.

    """
    _require_positive("nx", nx)
    _require_positive("ny", ny)
    _require_positive("a", a)
    j, i = np.meshgrid(np.arange(ny + 1), np.arange(nx + 1), indexing="ij")
    pts = np.zeros(((nx + 1) * (ny + 1), 3))
    pts[:, 0] = (a * (i + 0.5 * (j % 2))).ravel()
    pts[:, 1] = (a * np.sqrt(3.0) / 2.0 * j).ravel()
    v = _lattice_index(nx, ny)
    v00, v10, v01, v11 = v[:-1, :-1], v[:-1, 1:], v[1:, :-1], v[1:, 1:]
    even = (np.arange(ny) % 2 == 0)[:, None]
    t1 = np.where(even[..., None], np.stack([v00, v10, v01], -1), np.stack([v00, v11, v01], -1))
    t2 = np.where(even[..., None], np.stack([v10, v11, v01], -1), np.stack([v00, v10, v11], -1))
    faces = np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)]).astype(np.int64)
    return pts, faces


def grid_plate(nx: int, ny: int, lx: float = 1.0, ly: float = 1.0,
               diagonals: Literal["alternate", "right"] = "alternate") -> Mesh:
    """Rectangle ``[0, lx] x [0, ly]`` of ``nx x ny`` quads split into right triangles.

    Args:
        nx: Cells along x.
        ny: Cells along y.
        lx: Length along x.
        ly: Length along y.
        diagonals: "right" splits every quad along the same diagonal (from (i, j) to
            (i+1, j+1)); "alternate" flips the diagonal in a checkerboard pattern.

    Returns:
        (points, faces), faces counter-clockwise seen from +z.

    """
    _require_positive("nx", nx)
    _require_positive("ny", ny)
    _require_positive("lx", lx)
    _require_positive("ly", ly)
    if diagonals not in ("alternate", "right"):
        raise InputError(f"meshes.shells.grid_plate: diagonals must be 'alternate' or 'right', "
                         f"got {diagonals!r}")
    y, x = np.meshgrid(np.linspace(0, ly, ny + 1), np.linspace(0, lx, nx + 1), indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    v = _lattice_index(nx, ny)
    v00, v10, v01, v11 = v[:-1, :-1], v[:-1, 1:], v[1:, :-1], v[1:, 1:]
    jj, ii = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    flip = ((ii + jj) % 2 == 1) if diagonals == "alternate" else np.zeros_like(ii, dtype=bool)
    f = flip[..., None]
    t1 = np.where(f, np.stack([v00, v10, v01], -1), np.stack([v00, v10, v11], -1))
    t2 = np.where(f, np.stack([v10, v11, v01], -1), np.stack([v00, v11, v01], -1))
    faces = np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)]).astype(np.int64)
    return pts, faces


def wrap_on_cylinder(points: np.ndarray, radius: float) -> np.ndarray:
    """Isometrically roll a flat plate (z = 0) onto a cylinder of axis parallel to y.

    ``(x, y, 0) -> (R sin(x/R), y, R (1 - cos(x/R)))``: the axis is the line
    ``{(0, y, R)}``; arc length along x and lengths along y are preserved, the plate's +z
    normal becomes the inward normal (pointing towards the axis).

    Args:
        points: (n, 3) plate points with z = 0.
        radius: Cylinder radius R.

    Returns:
        (n, 3) wrapped points.

    """
    _require_positive("radius", radius)
    s = points[:, 0] / radius
    out = np.empty_like(points, dtype=np.float64)
    out[:, 0] = radius * np.sin(s)
    out[:, 1] = points[:, 1]
    out[:, 2] = radius * (1.0 - np.cos(s))
    return out


def cylinder_strip(nx: int, ny: int, radius: float, arc_length: float, length: float,
                   lattice: Literal["grid", "equilateral"] = "grid") -> Mesh:
    """Open cylindrical strip: a flat plate rolled by :func:`wrap_on_cylinder`.

    Args:
        nx: Cells around the circumference (along the arc).
        ny: Cells along the axis.
        radius: Cylinder radius R.
        arc_length: Arc length of the strip (< 2 pi R keeps it open).
        length: Axial length (used by the "grid" lattice; the "equilateral" lattice takes
            its edge length from ``arc_length / nx``).
        lattice: "grid" (alternate right triangles) or "equilateral".

    Returns:
        (points, faces), the flat plate's connectivity (normals towards the axis).

    """
    _require_positive("arc_length", arc_length)
    if arc_length >= 2 * np.pi * radius:
        raise InputError("meshes.shells.cylinder_strip: arc_length must be < 2 pi radius")
    if lattice == "grid":
        pts, faces = grid_plate(nx, ny, arc_length, length, "alternate")
    elif lattice == "equilateral":
        pts, faces = equilateral_plate(nx, ny, arc_length / (nx + 0.5))
    else:
        raise InputError(f"meshes.shells.cylinder_strip: unknown lattice {lattice!r}")
    return wrap_on_cylinder(pts, radius), faces


_ICO_FACES = np.array([
    [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
    [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
    [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)


def _icosahedron() -> Mesh:
    """Return the unit icosahedron (12 vertices, 20 outward-oriented faces)."""
    t = (1.0 + np.sqrt(5.0)) / 2.0
    p = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 dtype=np.float64)
    return p / np.linalg.norm(p, axis=1, keepdims=True), _ICO_FACES.copy()


def midpoint_subdivide(points: np.ndarray, faces: np.ndarray) -> Mesh:
    """One 1-to-4 midpoint subdivision (vectorised, orientation preserved).

    Args:
        points: (n, 3) vertices.
        faces: (F, 3) faces.

    Returns:
        (points, faces) with ``n + E`` vertices and ``4 F`` faces.

    """
    n = points.shape[0]
    he = np.stack([faces, np.roll(faces, -1, axis=1)], -1).reshape(-1, 2)
    key = np.sort(he, axis=1)
    uniq, inv = np.unique(key[:, 0] * n + key[:, 1], return_inverse=True)
    e = np.column_stack([uniq // n, uniq % n])
    mid = (n + inv).reshape(-1, 3)  # mid[f, a] = midpoint of edge (v_a, v_{a+1})
    new_pts = np.concatenate([points, 0.5 * (points[e[:, 0]] + points[e[:, 1]])])
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    mab, mbc, mca = mid[:, 0], mid[:, 1], mid[:, 2]
    new_faces = np.concatenate([np.column_stack(t) for t in (
        (a, mab, mca), (mab, b, mbc), (mca, mbc, c), (mab, mbc, mca))]).astype(np.int64)
    return new_pts, new_faces


def icosphere(level: int, radius: float = 1.0) -> Mesh:
    """Build a closed sphere: icosahedron, ``level`` midpoint subdivisions, projected.

    ``10 * 4**level + 2`` vertices (10242 at level 5, 40962 at 6, 163842 at 7, 655362 at 8).
    Vertex order: level by level (each subdivision appends the edge midpoints), so mesh
    neighbours are far apart in memory (mean |i - j| over the edges 3521 at level 5);
    renumber with :func:`models.shell.reorder.reorder_mesh` (125 with Morton, 89 with RCM)
    before building a shell whose kernels must be fast.

    Args:
        level: Subdivision levels (>= 0).
        radius: Sphere radius.

    Returns:
        (points, faces) with outward-oriented faces.

    """
    if level < 0:
        raise InputError(f"meshes.shells.icosphere: level must be >= 0, got {level}")
    _require_positive("radius", radius)
    pts, faces = _icosahedron()
    for _ in range(level):
        pts, faces = midpoint_subdivide(pts, faces)
        pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    return radius * pts, faces


def orient_ccw(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip planar faces (in the xy-plane) with negative signed area to counter-clockwise."""
    p = points[faces]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    neg = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] < 0
    out = faces.copy()
    out[neg] = out[neg][:, [0, 2, 1]]
    return out


def irregular_plate(n: int, seed: int = 0, jitter: float = 0.35) -> Mesh:
    """Unstructured unit-square plate: jittered random points + Delaunay (scipy).

    About ``n`` vertices: a ``m x m`` lattice (``m = round(sqrt(n))``) whose interior points are
    moved uniformly at random by up to ``jitter`` cells and whose boundary points slide along
    the boundary, so the Delaunay triangulation is irregular but free of hull slivers.

    Args:
        n: Target vertex count (>= 9).
        seed: Random seed.
        jitter: Random displacement in cell sizes (< 0.5 keeps points distinct).

    Returns:
        (points, faces), faces counter-clockwise seen from +z.

    """
    if n < 9:
        raise InputError(f"meshes.shells.irregular_plate: n must be >= 9, got {n}")
    if not 0.0 <= jitter < 0.5:
        raise InputError(f"meshes.shells.irregular_plate: jitter must be in [0, 0.5), got {jitter}")
    m = int(round(np.sqrt(n)))
    h = 1.0 / (m - 1)
    y, x = np.meshgrid(np.linspace(0, 1, m), np.linspace(0, 1, m), indexing="ij")
    xy = np.column_stack([x.ravel(), y.ravel()])
    rng = np.random.default_rng(seed)
    move = rng.uniform(-jitter * h, jitter * h, size=xy.shape)
    on_x = np.isclose(xy[:, 0], 0) | np.isclose(xy[:, 0], 1)
    on_y = np.isclose(xy[:, 1], 0) | np.isclose(xy[:, 1], 1)
    move[on_x, 0] = 0.0
    move[on_y, 1] = 0.0
    xy = xy + move
    tri = Delaunay(xy)
    pts = np.column_stack([xy, np.zeros(len(xy))])
    return pts, orient_ccw(pts, tri.simplices.astype(np.int64))


def perturb(x: np.ndarray, amplitude: float, seed: int = 0) -> np.ndarray:
    """Return ``x`` plus i.i.d. uniform noise in ``[-amplitude, amplitude]`` per coordinate."""
    rng = np.random.default_rng(seed)
    return x + rng.uniform(-amplitude, amplitude, size=x.shape)
