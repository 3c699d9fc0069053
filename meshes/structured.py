"""Structured (gmsh-free) tet meshes of boxes: the Freudenthal-Kuhn triangulation.

Each of the ``nx * ny * nz`` cells is split into the 6 tets ``(v, v + e_a, v + e_a + e_b,
v + e_a + e_b + e_c)`` for the permutations ``(a, b, c)`` of the axes (Freudenthal 1942,
Kuhn 1960). All cells use the same main diagonal, so the mesh is conforming; every tet has
volume ``dx dy dz / 6``. Regular meshes are what mesh-convergence studies and cross-checks
against other codes (scikit-fem) need, and they make small test bodies without gmsh.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from meshes.errors import InputError
from meshes.tetmesh import IntArray, TetMesh
from meshes.validate import validate


def _kuhn_local() -> IntArray:
    """(6, 4) local corner ids (bit k of an id = offset along axis k), positively oriented."""
    rows = []
    for perm in itertools.permutations(range(3)):
        corners = np.cumsum([0] + [1 << a for a in perm])
        if np.linalg.det(np.eye(3)[list(perm)]) < 0:
            corners[[2, 3]] = corners[[3, 2]]
        rows.append(corners)
    return np.array(rows, dtype=np.int64)


def _cells(shape: tuple[int, int, int]) -> tuple[IntArray, IntArray]:
    """Lower-corner vertex ids of every cell and the id offset of each of the 8 corners."""
    nx, ny, nz = shape
    strides = np.array([1, nx + 1, (nx + 1) * (ny + 1)], dtype=np.int64)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    base = (i * strides[0] + j * strides[1] + k * strides[2]).reshape(-1)
    bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1
    return base, bits @ strides


def structured_box(shape: Sequence[int], size: Sequence[float] = (1.0, 1.0, 1.0),
                   origin: Sequence[float] = (0.0, 0.0, 0.0)) -> TetMesh:
    """Freudenthal-Kuhn tet mesh of ``origin + [0, size]``, ``6 nx ny nz`` tets.

    Args:
        shape: Cells per axis ``(nx, ny, nz)``, each >= 1.
        size: Box edge lengths (m).
        origin: Lower corner (m).

    Returns:
        A validated :class:`TetMesh` with ``(nx+1)(ny+1)(nz+1)`` points, numbered x fastest.

    Raises:
        InputError: Naming ``shape``, ``size`` or ``origin`` when invalid.

    """
    n = tuple(int(v) for v in shape) if len(shape) == 3 else ()
    if len(n) != 3 or min(n) < 1 or any(int(v) != v for v in shape):
        raise InputError(f"structured_box: shape must be 3 integers >= 1, got {shape!r}")
    lengths, low = np.asarray(size, dtype=float), np.asarray(origin, dtype=float)
    if lengths.shape != (3,) or not (np.isfinite(lengths).all() and (lengths > 0).all()):
        raise InputError(f"structured_box: size must be 3 finite lengths > 0, got {size!r}")
    if low.shape != (3,) or not np.isfinite(low).all():
        raise InputError(f"structured_box: origin must be 3 finite numbers, got {origin!r}")
    axes = [np.linspace(low[a], low[a] + lengths[a], n[a] + 1) for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.stack([x.reshape(-1), y.reshape(-1), z.reshape(-1)], axis=1)
    base, offset = _cells((n[0], n[1], n[2]))
    tets = (base[:, None, None] + offset[_kuhn_local()][None, :, :]).reshape(-1, 4)
    source = f"structured_box(shape={n!r}, size={tuple(lengths.tolist())!r}, " \
             f"origin={tuple(low.tolist())!r})"
    return validate(TetMesh(points, tets, source))
