"""Coarse tetrahedral bodies as plain numpy arrays (no dolfinx).

- :class:`TetMesh`: points (n, 3) float64, tets (m, 4) int64, source, derived quantities.
- :func:`validate`: checks any tet mesh (builder output or raw arrays), raising InputError.
- :func:`load`: any meshio-readable tet mesh file, validated.
- :func:`box`, :func:`cylinder`, :func:`sphere`, :func:`sofa`: gmsh (OCC) builders, cached.
- :func:`structured_box`: gmsh-free Freudenthal-Kuhn box mesh (regular, 6 tets per cell).
- :func:`boundary_triangles`, :func:`boundary_surface`: the outward boundary surface.

Each name's module loads on the name's first use (PEP 562): ``meshes.errors``, which every
layer imports, loads neither meshio, scipy nor gmsh; loading a file does not load gmsh.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from meshes.builders import SofaDimensions, box, cylinder, sofa, sofa_parts, sphere
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

_HOME = {"load": "loader", "structured_box": "structured", "MeshWarning": "validate",
         "ValidationOptions": "validate", "validate": "validate"} | dict.fromkeys(
    ("TetMesh", "boundary_faces_with_cells", "boundary_surface", "boundary_triangles",
     "tet_components", "tet_volumes"), "tetmesh") | dict.fromkeys(
    ("box", "cylinder", "sphere", "sofa", "sofa_parts", "SofaDimensions"), "builders")
"""The module of each public name: imported on the name's first use."""

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
    """Import a public name's module on first use (PEP 562).

    ``import meshes.errors`` (every layer's error types) then loads neither meshio, scipy nor
    gmsh; the loader and the tet mesh load them when first used, the builders gmsh.
    """
    if name in _HOME:
        value = getattr(importlib.import_module(f"meshes.{_HOME[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'meshes' has no attribute {name!r}")


class _Package(types.ModuleType):
    """The package's module type: a public name is never shadowed by its own submodule.

    Python binds a submodule to its package's attribute when the submodule first loads, so
    ``meshes.validate`` (the function) would become the module ``meshes.validate`` wherever
    that module loaded first; the function stays bound instead.
    """

    def __setattr__(self, name: str, value: Any) -> None:
        """Bind ``value``, or the public name of that name's own submodule ``value``."""
        if isinstance(value, types.ModuleType) and value.__name__ == f"{__name__}.{name}" \
                and _HOME.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
