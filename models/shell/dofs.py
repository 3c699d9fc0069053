"""Degree-of-freedom conventions of the discrete shell (written once, used everywhere).

Conventions:
    * Positions ``x`` are an ``(n, 3)`` float64 array (one row per vertex).
    * The flat vector of unknowns is ``x.reshape(-1)`` (C order), so the dof of vertex ``i``,
      coordinate ``k`` is ``3 * i + k``. Gradients are flat ``(3 n,)`` arrays in this order and
      Hessians are ``(3 n, 3 n)`` sparse matrices made of 3x3 vertex blocks.
    * A *stencil* is an ``(m, s)`` int64 array of vertex indices (edges ``s = 2``, faces
      ``s = 3``, hinges ``s = 4``). A term's local Hessian of stencil ``t`` is a
      ``(3 s, 3 s)`` block whose row ``3 a + k`` is the dof ``3 * stencil[t, a] + k``.
"""

from __future__ import annotations

import numpy as np

from meshes.errors import InputError

DIM: int = 3
"""Spatial dimension: every vertex carries three dofs."""


def flat(x: np.ndarray) -> np.ndarray:
    """Flat dof vector of positions ``x`` (a view when ``x`` is C-contiguous)."""
    return np.ascontiguousarray(x, dtype=np.float64).reshape(-1)


def unflat(v: np.ndarray) -> np.ndarray:
    """Positions ``(n, 3)`` of a flat ``(3 n,)`` dof vector (a view)."""
    return np.asarray(v, dtype=np.float64).reshape(-1, DIM)


def stencil_dofs(stencils: np.ndarray) -> np.ndarray:
    """Global dofs ``(m, 3 s)`` of each stencil's local dofs, ``3 * stencil[:, a] + k``."""
    s = np.asarray(stencils, dtype=np.int64)
    return (DIM * s[:, :, None] + np.arange(DIM)).reshape(s.shape[0], -1)


def check_positions(x: np.ndarray, n_vertices: int, name: str = "x") -> np.ndarray:
    """Validate and return positions as a C-contiguous ``(n_vertices, 3)`` float64 array.

    Args:
        x: Positions, ``(n, 3)`` or flat ``(3 n,)``.
        n_vertices: Expected vertex count.
        name: Name used in the error message.

    Raises:
        InputError: wrong shape or non-finite entries.

    """
    a = np.ascontiguousarray(x, dtype=np.float64)
    if a.ndim == 1 and a.size == DIM * n_vertices:
        a = a.reshape(n_vertices, DIM)
    if a.shape != (n_vertices, DIM):
        raise InputError(f"{name}: expected shape ({n_vertices}, 3), got {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])
        raise InputError(f"{name}: non-finite coordinate at vertex {bad}")
    return a
