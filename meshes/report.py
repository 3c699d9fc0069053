"""What a user should know about an accepted tet mesh: pieces, cracks, slivers.

:func:`meshes.validate.validate` refuses meshes that cannot be used; this report describes
meshes that can be used but may not be what the user meant:

* ``components``: the tets form this many disconnected bodies (each one is simulated, the
  pieces only interact through contacts);
* ``coincident_points``: distinct points at the same position (closer than ``1e-9`` of the
  bounding-box diagonal), e.g. a crack or an unmerged seam: the two sides do not hold together;
* ``min_quality`` and ``low_quality``: the tet shape quality ``6 sqrt(2) V / l_rms^3`` (1 for a
  regular tet, 0 for a sliver; ``l_rms`` the root mean square edge length) and the number of
  tets below :data:`LOW_QUALITY`, which slow the body's Newton and stiffen its response.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from meshes.tetmesh import TetMesh, tet_volumes

LOW_QUALITY: float = 0.1
"""Tets below this shape quality are counted as slivers."""
COINCIDENT_TOLERANCE: float = 1e-9
"""Points closer than this fraction of the bounding-box diagonal are coincident."""


@dataclass(frozen=True)
class MeshReport:
    """Facts of an accepted mesh (module docstring).

    Attributes:
        components: connected pieces (tets sharing a vertex are connected).
        coincident_points: points that coincide with another point.
        min_quality: smallest tet shape quality.
        low_quality: tets of quality below :data:`LOW_QUALITY`.

    """

    components: int
    coincident_points: int
    min_quality: float
    low_quality: int

    def warnings(self, source: str) -> list[str]:
        """One message per fact a user should see, naming the mesh ``source``."""
        out = []
        if self.components > 1:
            out.append(f"{source}: {self.components} disconnected bodies (the pieces interact "
                       f"only through contacts)")
        if self.coincident_points:
            out.append(f"{source}: {self.coincident_points} points coincide with another point "
                       f"(a crack or an unmerged seam: its sides do not hold together)")
        if self.low_quality:
            out.append(f"{source}: {self.low_quality} tets of shape quality below "
                       f"{LOW_QUALITY} (worst {self.min_quality:.3g}; 1 = regular)")
        return out


def tet_quality(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Return ``6 sqrt(2) |V| / l_rms^3`` of every tet (1 regular, 0 degenerate)."""
    p = points[tets]
    pairs = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    l2 = sum(np.sum((p[:, i] - p[:, j]) ** 2, axis=1) for i, j in pairs) / 6.0
    return 6.0 * np.sqrt(2.0) * np.abs(tet_volumes(points, tets)) / np.maximum(l2, 1e-300) ** 1.5


def triangle_quality(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Return ``4 sqrt(3) A / (|e_0|^2 + |e_1|^2 + |e_2|^2)`` of every triangle.

    1 for an equilateral triangle, 0 for a degenerate one (``q ~ A / l^2`` when ``A << l^2``).
    """
    p = points[faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    edges2 = np.sum(np.sum((p - np.roll(p, 1, axis=1)) ** 2, axis=2), axis=1)
    return 4.0 * np.sqrt(3.0) * area / edges2


def components(n_points: int, tets: np.ndarray) -> int:
    """Return the number of connected pieces of the tets (through shared vertices)."""
    rows = np.repeat(tets[:, 0], 3)
    cols = tets[:, 1:].ravel()
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n_points, n_points))
    _, labels = connected_components(graph, directed=False)
    return int(np.unique(labels[np.unique(tets)]).size)


def coincident_points(points: np.ndarray) -> int:
    """Return how many points lie at the position of another point (to the tolerance)."""
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) or 1.0
    keys = np.round(points / (COINCIDENT_TOLERANCE * diagonal)).astype(np.int64)
    _, counts = np.unique(keys, axis=0, return_counts=True)
    return int(counts[counts > 1].sum())


def mesh_report(mesh: TetMesh) -> MeshReport:
    """Return the :class:`MeshReport` of a validated mesh."""
    quality = tet_quality(mesh.points, mesh.tets)
    return MeshReport(components=components(mesh.n_points, mesh.tets),
                      coincident_points=coincident_points(mesh.points),
                      min_quality=float(quality.min()),
                      low_quality=int(np.count_nonzero(quality < LOW_QUALITY)))


__all__ = ["COINCIDENT_TOLERANCE", "LOW_QUALITY", "MeshReport", "components", "coincident_points",
           "mesh_report", "tet_quality", "triangle_quality"]
