"""Load any tetrahedral mesh file meshio reads (.msh, .vtu, .vtk, .xdmf, .mesh, .med, ...).

The loader keeps the tetra cells only (the corner vertices of ``tetra10`` cells are taken as
linear tets), drops the points no tet uses and validates the result with
:func:`meshes.validate.validate`. Every failure is an :class:`InputError` whose one-line
message names the file (and the element, for mesh defects).
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from pathlib import Path

import meshio
import numpy as np

from meshes.errors import InputError
from meshes.tetmesh import TetMesh
from meshes.validate import MeshWarning, ValidationOptions, resolve_options, validate

#: meshio cell types read as linear tets, with the columns that are their corners.
TET_CELL_TYPES: dict[str, slice] = {"tetra": slice(0, 4), "tetra10": slice(0, 4)}
#: meshio cell types of volume cells this code cannot use (a file holding any is refused).
OTHER_VOLUME_TYPES: tuple[str, ...] = (
    "hexahedron", "hexahedron20", "hexahedron24", "hexahedron27", "wedge", "wedge12", "wedge15",
    "wedge18", "pyramid", "pyramid13", "pyramid14", "polyhedron", "VTK_LAGRANGE_HEXAHEDRON",
    "VTK_LAGRANGE_WEDGE", "VTK_LAGRANGE_PYRAMID")


def read_meshio(path: Path) -> meshio.Mesh:
    """Read ``path`` with meshio, turning every failure into an InputError naming the file.

    Raises:
        InputError: Missing file, unknown format or unreadable content.

    """
    if not path.is_file():
        raise InputError(f"{path}: no such mesh file")
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            return meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types, even sys.exit(1)
        lines = [ln.strip() for ln in [*str(exc).splitlines(), *chatter.getvalue().splitlines()]
                 if ln.strip() and ln.strip() != "1"]
        reason = " ".join(lines)[:200] or type(exc).__name__
        raise InputError(f"{path}: cannot read mesh ({reason})") from None


def tet_cells(mesh: meshio.Mesh, source: str) -> np.ndarray:
    """Concatenate the tetra (and tetra10 corner) cell blocks of a meshio mesh.

    Surface and line cells (boundary tags) are ignored; other volume cells are refused, since
    dropping them would silently lose part of the body.

    Raises:
        InputError: The file has no tetrahedra, or volume cells other than tetrahedra; the
            message lists the cell types and their counts.

    """
    counts: dict[str, int] = {}
    for block in mesh.cells:
        if len(block.data) and (block.type in OTHER_VOLUME_TYPES
                                or block.type.startswith("polyhedron")):
            counts[block.type] = counts.get(block.type, 0) + len(block.data)
    if counts:
        found = ", ".join(f"{n} {kind}" for kind, n in sorted(counts.items()))
        raise InputError(f"{source}: volume cells other than tetrahedra ({found}); only "
                         f"tetrahedral meshes can be used (convert the mesh, e.g. with gmsh)")
    blocks = [np.asarray(b.data)[:, TET_CELL_TYPES[b.type]] for b in mesh.cells
              if b.type in TET_CELL_TYPES and len(b.data)]
    if not blocks:
        found = (", ".join(sorted({b.type for b in mesh.cells if len(b.data)}))
                 or f"no cells, {len(mesh.points)} points: empty mesh")
        raise InputError(f"no tetrahedra in {source} (found: {found})")
    return np.concatenate(blocks, axis=0)


def load(path: str | os.PathLike[str], options: ValidationOptions | None = None,
         **overrides: bool | float) -> TetMesh:
    """Load a tet mesh file into a validated :class:`TetMesh`.

    Args:
        path: Any file meshio can read.
        options: Validation tolerances and repairs (``fix_orientation`` on by default:
            inverted tets are re-oriented with a ``MeshWarning``).
        **overrides: Fields of ``options`` to replace, e.g. ``fix_orientation=False``.

    Returns:
        The validated mesh; ``source`` is the file path.

    Raises:
        InputError: Missing or unreadable file, no tets, or a mesh defect (see
            :func:`meshes.validate.validate`), naming the file and the element.

    """
    opts = resolve_options(options, overrides)
    p = Path(path)
    mesh = read_meshio(p)
    tets = tet_cells(mesh, str(p))
    ignored = ignored_cell_data(mesh)
    if ignored:
        warnings.warn(f"{p}: cell data ignored, one material for the whole body: "
                      f"{ignored}", MeshWarning, stacklevel=2)
    return validate(mesh.points, tets, source=str(p), options=opts)


def ignored_cell_data(mesh: meshio.Mesh) -> str:
    """Describe the tets' cell data with several values (regions, materials) left unused."""
    parts = []
    for name, blocks in mesh.cell_data.items():
        values = [np.asarray(data) for block, data in zip(mesh.cells, blocks, strict=False)
                  if block.type in TET_CELL_TYPES and len(data)]
        distinct = np.unique(np.concatenate(values)) if values else np.zeros(0)
        if distinct.size > 1:  # one value tags one region: nothing to lose
            shown = ", ".join(str(v) for v in distinct[:6]) + (", ..." if distinct.size > 6 else "")
            parts.append(f"{name} ({distinct.size} values: {shown})")
    return "; ".join(parts)
