"""Coarse tetrahedral bodies as plain numpy arrays (no dolfinx).

- :class:`TetMesh`: points (n, 3) float64, tets (m, 4) int64, source, derived quantities.
- :func:`validate`: checks any tet mesh (builder output or raw arrays), raising InputError.
- :func:`load`: any meshio-readable tet mesh file, validated.
- :func:`box`, :func:`cylinder`, :func:`sphere`, :func:`sofa`: gmsh (OCC) builders, cached.
- :func:`structured_box`: gmsh-free Freudenthal-Kuhn box mesh (regular, 6 tets per cell).
- :func:`boundary_triangles`, :func:`boundary_surface`: the outward boundary surface.

The builders import gmsh lazily (on first access), so loading a file does not load gmsh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from meshes.loader import load
from meshes.structured import structured_box
from meshes.tetmesh import (
    TetMesh,
    boundary_faces_with_cells,
    boundary_surface,
    boundary_triangles,
    tet_components,
    tet_volumes,
)
from meshes.validate import MeshWarning, ValidationOptions, validate

if TYPE_CHECKING:
    from meshes.builders import SofaDimensions, box, cylinder, sofa, sofa_parts, sphere

_BUILDERS = {"box", "cylinder", "sphere", "sofa", "sofa_parts", "SofaDimensions"}

__all__ = [
    "MeshWarning",
    "SofaDimensions",
    "TetMesh",
    "ValidationOptions",
    "boundary_faces_with_cells",
    "boundary_surface",
    "boundary_triangles",
    "box",
    "cylinder",
    "load",
    "sofa",
    "sofa_parts",
    "sphere",
    "structured_box",
    "tet_components",
    "tet_volumes",
    "validate",
]


def __getattr__(name: str) -> Any:
    """Import the gmsh builders on first use (PEP 562)."""
    if name in _BUILDERS:
        from meshes import builders

        return getattr(builders, name)
    raise AttributeError(f"module 'meshes' has no attribute {name!r}")
