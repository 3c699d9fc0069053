"""Run output: the body XDMF/HDF5 time series and the run summary (JSON).

``body.xdmf`` + ``body.h5`` are written through ``dolfinx.io.XDMFFile``: the mesh once, then the
initial state (t = 0) and each output frame: the named fields ``displacement`` and ``velocity``
(P2 fields interpolated to P1, the geometry degree, since XDMF stores nodal values) at the
physical time. The file is opened in append mode and closed again for each frame, so the HDF5
data of every completed frame is on disk if the run is killed (a kill *during* the few ms of a
write can still leave the HDF5 file damaged: HDF5 has no journal). dolfinx writes one temporal
collection per field; after each frame rank 0 rewrites the XML so that each time step is one
grid carrying all fields (the layout ParaView and ``meshio.xdmf.TimeSeriesReader`` both read).
The heavy data is not touched.

``summary.json`` holds the resolved scene, package versions and one record per frame (time,
Newton iterations, energy, min det F, wall times); rank 0 rewrites it atomically (temporary
file + ``os.replace``) after every frame.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from models.backend import MPI, PETSc, dolfinx
from models.errors import InputError
from wrinkles.collective import on_root

XDMF_NAME = "body.xdmf"
SUMMARY_NAME = "summary.json"
FIELDS: tuple[str, ...] = ("displacement", "velocity")
PACKAGES: tuple[str, ...] = ("dolfinx-solver-real", "numpy", "scipy", "mpi4py", "meshio",
                             "gmsh", "h5py", "numba", "scikit-fem")
XI = "{https://www.w3.org/2001/XInclude}"


@dataclass(frozen=True)
class OutputOptions:
    """Which output files a run writes and how often.

    Attributes:
        xdmf: write the body time series ``body.xdmf`` + ``body.h5``.
        every: write the XDMF fields every N-th frame (the last frame is always written); >= 1.
        summary: write ``summary.json`` (resolved scene, versions, per-frame records).
        checkpoint: write ``checkpoint.h5`` (body state of the last completed frame) so that
            ``wrinkles run --restart`` can continue the run.

    """

    xdmf: bool = True
    every: int = 1
    summary: bool = True
    checkpoint: bool = True

    def __post_init__(self) -> None:
        if self.every < 1:
            raise InputError(f"output.every must be >= 1, got {self.every}")

    def writes_frame(self, frame: int, last: int) -> bool:
        """Tell whether frame ``frame`` (1-based) goes to the XDMF file (every N-th, last)."""
        return self.xdmf and (frame % self.every == 0 or frame == last)


# --------------------------------------------------------------------------------------------
# XDMF time series


def p1_function(u: dolfinx.fem.Function, name: str) -> dolfinx.fem.Function:
    """Make a named vector P1 function on ``u``'s mesh, to hold ``u`` at the mesh nodes."""
    mesh = u.function_space.mesh
    V1 = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (mesh.geometry.dim,)))
    return dolfinx.fem.Function(V1, name=name)


class XdmfSeries:
    """An XDMF/HDF5 time series of named vector fields on one mesh (collective calls).

    The mesh is written once at construction; :meth:`write` appends one time step, with
    each field interpolated into P1 (exact for P1, nodal values for P2), closes the file so
    the HDF5 data is on disk, and merges the XML into one grid per time step.

    Args:
        path: the ``.xdmf`` file (the ``.h5`` file goes beside it).
        fields: output name -> vector field (P1 or P2), e.g. ``{"displacement": u}``.
        resume_after: ``None`` to start a new file; for a restart, the time [s] of the
            restored state: the existing file is kept and its steps after that time are
            removed (XML and HDF5 data), so the rerun frames replace them.

    """

    def __init__(self, path: Path, fields: Mapping[str, dolfinx.fem.Function],
                 resume_after: float | None = None) -> None:
        self.path = path
        self.fields = dict(fields)
        self._nodal = {name: p1_function(u, name) for name, u in self.fields.items()}
        mesh = next(iter(self.fields.values())).function_space.mesh
        self.comm = mesh.comm
        if resume_after is None:
            with dolfinx.io.XDMFFile(self.comm, str(path), "w") as xdmf:
                xdmf.write_mesh(mesh)
        else:
            geometry = written_geometry(mesh)
            on_root(self.comm, lambda: resume_file(path, geometry, resume_after))

    def write(self, t: float) -> None:
        """Append the current values of the fields at physical time ``t`` [s]."""
        for name, u in self.fields.items():
            self._nodal[name].interpolate(u)
        with dolfinx.io.XDMFFile(self.comm, str(self.path), "a") as xdmf:
            for u1 in self._nodal.values():
                xdmf.write_function(u1, t)
        if self.comm.rank == 0:
            merge_time_collections(self.path)
        self.comm.barrier()


def _step_key(grid: ET.Element) -> str:
    """Return the ``Time Value`` of a step grid (the merge key)."""
    time = grid.find("Time")
    return time.get("Value", "0") if time is not None else "0"


def merge_time_collections(path: Path) -> None:
    """Rewrite an XDMF file so all temporal collections become one, one grid per time.

    dolfinx writes each field as its own ``Collection``; the merged layout puts every field's
    ``Attribute`` of a given time into one ``Uniform`` grid, which ``meshio`` reads as point
    data of one step. Idempotent: merging a merged file changes nothing.
    """
    tree = ET.parse(path)
    domain = tree.getroot().find("Domain")
    if domain is None:
        raise InputError(f"{path}: XDMF file without a Domain")
    collections = [g for g in domain.findall("Grid") if g.get("CollectionType") == "Temporal"]
    steps: dict[str, ET.Element] = {}
    for collection in collections:
        domain.remove(collection)
        for grid in collection.findall("Grid"):
            _merge_step(steps, grid)
    merged = ET.SubElement(domain, "Grid", Name="fields", GridType="Collection",
                           CollectionType="Temporal")
    merged.extend(sorted(steps.values(), key=lambda g: float(_step_key(g))))
    ET.indent(tree, "  ")
    tmp = path.with_suffix(".xdmf.tmp")
    tree.write(tmp, xml_declaration=True, encoding="utf-8")
    os.replace(tmp, path)


def _merge_step(steps: dict[str, ET.Element], grid: ET.Element) -> None:
    """Add ``grid``'s attributes to the step grid of the same time (created on first sight)."""
    key = _step_key(grid)
    if key not in steps:
        grid.set("Name", f"step_{len(steps)}")
        steps[key] = grid
        return
    names = {a.get("Name") for a in steps[key].findall("Attribute")}
    for attribute in grid.findall("Attribute"):
        if attribute.get("Name") not in names:
            steps[key].append(attribute)


def written_geometry(mesh: dolfinx.mesh.Mesh) -> np.ndarray | None:
    """Gather the node coordinates in the order ``XDMFFile.write_mesh`` stores them.

    Each rank writes its owned geometry nodes, in rank order (collective; the array is
    returned on rank 0, ``None`` elsewhere).
    """
    owned = mesh.geometry.index_map().size_local
    parts = mesh.comm.gather(mesh.geometry.x[:owned].copy(), root=0)
    return None if parts is None else np.concatenate(parts)


def resume_file(path: Path, geometry: np.ndarray | None, t: float) -> None:
    """Check that new steps can be appended to ``path``, then drop its steps after ``t``.

    Appended nodal values follow the node order of this run's partition, so the mesh stored
    in the file must have exactly that order (same mesh, same number of ranks).

    Raises:
        InputError: no such file, or its mesh is stored in another node order.

    """
    h5_path = path.with_suffix(".h5")
    if not (path.is_file() and h5_path.is_file()):
        raise InputError(f"{path}: no XDMF time series to continue")
    with h5py.File(h5_path, "r") as h5:
        stored = h5["Mesh/mesh/geometry"][...]
    if geometry is None or stored.shape != geometry.shape or not np.array_equal(stored,
                                                                                geometry):
        raise InputError(f"{path}: its mesh was written with another node order (another "
                         "number of MPI ranks?); restart on the original number of ranks, or "
                         "with --set output.xdmf=false")
    drop_steps_after(path, t)


def drop_steps_after(path: Path, t: float) -> None:
    """Remove the steps later than ``t`` [s] from an XDMF file and their HDF5 data."""
    merge_time_collections(path)
    tree = ET.parse(path)
    late = [(c, g) for c in tree.getroot().iter("Grid") for g in c.findall("Grid")
            if float(_step_key(g)) > t + 1e-12 * max(1.0, abs(t))]
    datasets = [item.text.split(":", 1)[1] for _, g in late
                for item in g.iter("DataItem") if item.text and ":" in item.text]
    with h5py.File(path.with_suffix(".h5"), "a") as h5:
        for name in datasets:
            if name.strip() in h5:
                del h5[name.strip()]
    for collection, grid in late:
        collection.remove(grid)
    tmp = path.with_suffix(".xdmf.tmp")
    tree.write(tmp, xml_declaration=True, encoding="utf-8")
    os.replace(tmp, path)


ET.register_namespace("xi", XI[1:-1])


# --------------------------------------------------------------------------------------------
# Summary JSON


def package_versions() -> dict[str, str]:
    """Versions of Python, PETSc, dolfinx and the scientific packages of this run."""
    versions = {"python": platform.python_version(), "dolfinx": dolfinx.__version__,
                "petsc": ".".join(str(v) for v in PETSc.Sys.getVersion()),
                "petsc4py": str(getattr(sys.modules.get("petsc4py"), "__version__", "?")),
                "mpi": MPI.Get_library_version().splitlines()[0].strip()}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


def write_json_atomic(path: Path, data: Any) -> None:
    """Write ``data`` as JSON to ``path`` atomically (temporary file + ``os.replace``)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n")
    os.replace(tmp, path)


def summary_document(scene: Mapping[str, Any], run: Mapping[str, Any],
                     frames: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Assemble the summary: scene, versions, run facts and frame records (JSON-able)."""
    return {"scene": dict(scene), "versions": package_versions(), "run": dict(run),
            "frames": [dict(f) for f in frames]}
