"""Run output: the body XDMF/HDF5 time series and the run summary (JSON).

``body.xdmf`` + ``body.h5`` are written through ``dolfinx.io.XDMFFile``: the mesh once, then the
initial state (t = 0) and each output frame: the named fields ``displacement`` and ``velocity``
(P2 fields interpolated to P1, the geometry degree, since XDMF stores nodal values) at the
physical time. dolfinx writes one temporal collection per field; rank 0 rewrites the XML so
that each time step is one grid carrying all fields (the layout ParaView and
``meshio.xdmf.TimeSeriesReader`` both read).

Kill safety and cost per frame. HDF5 has no journal and dolfinx rewrites the XML in place,
so a process killed *during* a write could leave either file damaged and lose every frame.
Each output frame is therefore written into a file of its own: all ranks write the step into
``.work/body.xdmf`` + ``.work/body.h5`` (a fresh file: the mesh and the step's fields), then
rank 0 ``os.replace``-s that HDF5 file to ``body.steps/step_<k>.h5`` and commits the XML:
the step's grids, their data items pointing at the step file, are merged into ``body.xdmf``
through a temporary file + ``os.replace``. Both renames are atomic and the XML is replaced
after the HDF5 file is in place, so at any instant ``body.xdmf`` is complete and references
only data on disk: a run killed at any moment keeps every completed frame readable. A frame
costs O(size of the frame) in HDF5 bytes plus the rewrite of the XML (about 1 kB per step).
``body.h5`` holds the mesh only. The shell series (:mod:`wrinkles.shell_output`) uses the
same per-step files. :func:`complete_steps` lists the steps whose data is actually readable.

``summary.json`` holds the resolved scene, package versions and one record per frame (time,
Newton iterations, energy, min det F, wall times; one line per record); rank 0 rewrites it
atomically (temporary file + ``os.replace``) after every frame.
"""

from __future__ import annotations

import functools
import json
import math
import os
import platform
import shutil
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from meshes.errors import InputError
from models.backend import MPI, PETSc, dolfinx
from wrinkles.collective import on_root
from wrinkles.provenance import wrinkles_version

XDMF_NAME = "body.xdmf"
SUMMARY_NAME = "summary.json"
FIELDS: tuple[str, ...] = ("displacement", "velocity")
PACKAGES: tuple[str, ...] = ("dolfinx-solver-real", "numpy", "scipy", "mpi4py", "meshio",
                             "gmsh", "h5py", "numba", "scikit-fem")
XI = "{http://www.w3.org/2001/XInclude}"
"""The XInclude namespace libxml2 expands (ParaView's legacy XDMF reader, ``vtkXdmfReader``,
pyvista); dolfinx 0.11 writes ``https://...``, which those readers do not expand."""
XI_HTTPS = "https://www.w3.org/2001/XInclude"
XML_HEADER = "<?xml version='1.0' encoding='utf-8'?>\n"
WORK_DIR = ".work"
"""Sub-directory of the output directory where a frame is written before it is committed."""
STEPS_SUFFIX = ".steps"
"""``<series stem><STEPS_SUFFIX>/step_<k>.h5``: the HDF5 file of step k of a series."""


@dataclass(frozen=True)
class OutputOptions:
    """Which output files a run writes and how often.

    ``summary.json`` and ``checkpoint.h5`` (the state of the last completed frame, which
    ``wrinkles run --resume`` continues from) are always written.

    Attributes:
        xdmf: write the body time series ``body.xdmf`` + ``body.h5``.
        every: write the XDMF fields every N-th frame (the last frame is always written); >= 1.
        render: after a run with a shell, write ``shell.png``, per-frame PNGs and
            ``shell.gif`` (:mod:`wrinkles.render`).

    """

    xdmf: bool = True
    every: int = 1
    render: bool = False

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

    The mesh is written once at construction (``body.h5``); :meth:`write` writes one time
    step, with each field interpolated into P1 (exact for P1, nodal values for P2), into its
    own HDF5 file and commits it (module doc: the frame appears in ``path`` all at once or
    not at all, at a cost proportional to the frame).

    Args:
        path: the ``.xdmf`` file (the mesh's ``.h5`` file and the ``.steps/`` directory go
            beside it).
        fields: output name -> vector field (P1 or P2), e.g. ``{"displacement": u}``.
        resume_after: ``None`` to start a new file; for a restart, the time [s] of the
            restored state: the existing file is kept (its mesh and node order; a run on
            another number of ranks writes its steps in that order) and its steps after that
            time are removed (XML and HDF5 data), so the rerun frames replace them.

    """

    def __init__(self, path: Path, fields: Mapping[str, dolfinx.fem.Function],
                 resume_after: float | None = None) -> None:
        self.path = path
        self.work = path.parent / WORK_DIR / path.name
        self.fields = dict(fields)
        self._nodal = {name: p1_function(u, name) for name, u in self.fields.items()}
        self.mesh = next(iter(self.fields.values())).function_space.mesh
        self.comm = self.mesh.comm
        self._order: np.ndarray | None = None  # rank 0: the file's node order, if another
        on_root(self.comm, lambda: self.work.parent.mkdir(parents=True, exist_ok=True))
        if resume_after is None:
            with dolfinx.io.XDMFFile(self.comm, str(self.work), "w") as xdmf:
                xdmf.write_mesh(self.mesh)
            on_root(self.comm, lambda: commit_frame(
                self.path, self.work, lambda: merge_time_collections(self.work, self.path)))
        else:
            geometry = written_geometry(self.mesh)
            self._order = on_root(self.comm, lambda: resume_file(path, geometry, resume_after))

    def write(self, t: float) -> None:
        """Write the current values of the fields at physical time ``t`` [s] and commit."""
        for name, u in self.fields.items():
            self._nodal[name].interpolate(u)
        with dolfinx.io.XDMFFile(self.comm, str(self.work), "w") as xdmf:
            xdmf.write_mesh(self.mesh)  # a step file without a mesh makes dolfinx warn
            for u1 in self._nodal.values():
                xdmf.write_function(u1, t)
        on_root(self.comm, self._commit)

    def _commit(self) -> None:
        """Commit the step in ``work`` (rank 0), its nodal values in the file's node order."""
        if self._order is not None:
            reorder_fields(self.work.with_suffix(".h5"), self._order)
        commit_step(self.path, self.work)


def steps_dir(path: Path) -> Path:
    """Directory of the per-step HDF5 files of the series ``path`` (``<stem>.steps``)."""
    return path.with_name(path.stem + STEPS_SUFFIX)


def step_file(path: Path, index: int) -> Path:
    """HDF5 file of step ``index`` (0-based, in time order) of the series ``path``."""
    return steps_dir(path) / f"step_{index:06d}.h5"


def count_steps(root: ET.Element) -> int:
    """Count the time steps (grids inside grid collections) of a parsed XDMF root element."""
    return sum(1 for c in root.iter("Grid") for _ in c.findall("Grid"))


def parse_xdmf(path: Path) -> ET.ElementTree[ET.Element[str]]:
    """Parse an XDMF file, with dolfinx's ``https`` XInclude namespace read as :data:`XI`.

    Every XML file of a series passes through here before it is written again, so the files
    on disk always carry the namespace libxml2-based readers expand.
    """
    text = path.read_text(encoding="utf-8").replace(XI_HTTPS, XI[1:-1])
    return ET.ElementTree(ET.fromstring(text))


def commit_step(path: Path, work: Path) -> None:
    """Commit a step dolfinx wrote into ``work`` (rank 0): move its HDF5 file, merge its XML.

    The HDF5 file becomes ``step_file(path, k)`` (``k`` = steps listed so far; a file left
    by a dropped step of that index is replaced) by ``os.replace``; only then the step's
    grids, their data items re-pointed at that file, are merged into ``path``'s XML.
    """
    tree, new = parse_xdmf(path), parse_xdmf(work)
    dest = step_file(path, count_steps(tree.getroot()))
    dest.parent.mkdir(parents=True, exist_ok=True)
    os.replace(work.with_suffix(".h5"), dest)
    domain, relative = tree.getroot().find("Domain"), dest.relative_to(path.parent).as_posix()
    if domain is None:
        raise InputError(f"{path}: XDMF file without a Domain")
    for collection in _temporal(new.getroot().find("Domain")):
        for item in collection.iter("DataItem"):
            if item.text and ":" in item.text:
                item.text = f"{relative}:{item.text.split(':', 1)[1].strip()}"
        domain.append(collection)
    merge_tree(tree, path, path)


def commit_frame(path: Path, work: Path, write_xml: Callable[[], None]) -> None:
    """Move ``work``'s HDF5 file over ``path``'s (rank 0), then call ``write_xml``.

    ``os.replace`` is atomic, and ``write_xml`` (which must write ``path`` atomically) runs
    only afterwards, so at any instant the XML on disk references only data on disk. Used
    for the series' first file (the mesh); steps go through :func:`commit_step`.
    """
    os.replace(work.with_suffix(".h5"), path.with_suffix(".h5"))
    write_xml()


def write_xml_atomic(tree: ET.ElementTree[ET.Element[str]], path: Path) -> None:
    """Write an XDMF tree to ``path`` through a temporary file and ``os.replace``.

    The ``xi`` namespace stays declared on the root even when no ``xi:include`` is left
    (ElementTree drops unused declarations; dolfinx appends ``xi:include`` without one).
    """
    ET.indent(tree, "  ")
    text = ET.tostring(tree.getroot(), encoding="unicode")
    if "xmlns:xi=" not in text.split(">", 1)[0]:
        text = text.replace("<Xdmf", f'<Xdmf xmlns:xi="{XI[1:-1]}"', 1)
    write_text_atomic(path, XML_HEADER + text + "\n")


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file + ``os.replace``."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _step_key(grid: ET.Element) -> str:
    """Return the ``Time Value`` of a step grid (the merge key)."""
    time = grid.find("Time")
    return time.get("Value", "0") if time is not None else "0"


def _temporal(domain: ET.Element | None) -> list[ET.Element]:
    """Return the temporal collections directly under an XDMF ``Domain``."""
    if domain is None:
        return []
    return [g for g in domain.findall("Grid") if g.get("CollectionType") == "Temporal"]


def merge_tree(tree: ET.ElementTree[ET.Element[str]], path: Path, dest: Path) -> None:
    """Merge the temporal collections of an XDMF tree into one and write it to ``dest``.

    Every field's ``Attribute`` of a given time goes into one ``Uniform`` grid (sorted by
    time). ``path`` names the file in error messages.
    """
    domain = tree.getroot().find("Domain")
    if domain is None:
        raise InputError(f"{path}: XDMF file without a Domain")
    steps: dict[str, ET.Element] = {}
    for collection in _temporal(domain):
        domain.remove(collection)
        for grid in collection.findall("Grid"):
            _merge_step(steps, grid)
    merged = ET.SubElement(domain, "Grid", Name="fields", GridType="Collection",
                           CollectionType="Temporal")
    merged.extend(sorted(steps.values(), key=lambda g: float(_step_key(g))))
    write_xml_atomic(tree, dest)


def merge_time_collections(path: Path, dest: Path | None = None) -> None:
    """Rewrite an XDMF file so all temporal collections become one, one grid per time.

    dolfinx writes each field as its own ``Collection``; the merged layout puts every field's
    ``Attribute`` of a given time into one ``Uniform`` grid, which ``meshio`` reads as point
    data of one step. Idempotent: merging a merged file changes nothing. The result goes to
    ``dest`` (default ``path``) atomically.
    """
    merge_tree(parse_xdmf(path), path, dest or path)


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


def resume_file(path: Path, geometry: np.ndarray | None, t: float) -> np.ndarray | None:
    """Check that new steps can be appended to ``path``, drop its steps after ``t``.

    Appended nodal values follow the node order of this run's partition (``geometry``, the
    nodes as :func:`written_geometry` gathers them); a file written on another number of
    ranks stores the same nodes in another order, and the steps of this run are then
    permuted into the file's order (:func:`node_order`, :func:`reorder_fields`).

    Returns:
        The permutation ``p`` with ``geometry[p]`` in the file's order, None when the orders
        agree.

    Raises:
        InputError: no such file, or its mesh has other nodes (another mesh).

    """
    h5_path = path.with_suffix(".h5")
    if not (path.is_file() and h5_path.is_file()):
        raise InputError(f"{path}: no XDMF time series to continue")
    with h5py.File(h5_path, "r") as h5:
        stored = h5["Mesh/mesh/geometry"][...]
    order = node_order(stored, geometry)
    if order is None:
        raise InputError(f"{path}: its mesh has other nodes than this run's ({stored.shape[0]} "
                         f"stored); continue with the scene that wrote it, or --set "
                         f"output.xdmf=false")
    drop_steps_after(path, t)
    return None if np.array_equal(order, np.arange(order.size)) else order


def node_order(stored: np.ndarray, geometry: np.ndarray | None) -> np.ndarray | None:
    """Return ``p`` with ``geometry[p] == stored`` row by row, or None if no such ``p``.

    The nodes are matched by their coordinates, which a repartitioned mesh keeps bitwise
    (dolfinx moves nodes between ranks, it does not recompute them).
    """
    if geometry is None or stored.shape != geometry.shape:
        return None
    by_stored = np.lexsort(stored.T[::-1])
    by_geometry = np.lexsort(geometry.T[::-1])
    if not np.array_equal(stored[by_stored], geometry[by_geometry]):
        return None
    order = np.empty(stored.shape[0], dtype=np.int64)
    order[by_stored] = by_geometry
    return order


def reorder_fields(h5_path: Path, order: np.ndarray) -> None:
    """Permute the node rows of every field dataset (``/Function/...``) of a step file."""
    with h5py.File(h5_path, "r+") as h5:
        if "Function" not in h5:
            return
        datasets: list[h5py.Dataset] = []
        h5["Function"].visititems(
            lambda _name, obj: datasets.append(obj) if isinstance(obj, h5py.Dataset) else None)
        for data in datasets:
            if data.shape[0] == order.size:
                data[...] = data[...][order]


def drop_steps_after(path: Path, t: float) -> None:
    """Remove the steps later than ``t`` [s] from an XDMF file and their HDF5 data.

    The XML without those steps is committed first, then their data is removed: a step file
    (``<stem>.steps/step_<k>.h5``) no remaining step references is deleted; datasets of older
    runs stored in the series' own ``.h5`` file (the layout before per-step files) are
    removed from a copy that replaces it. A kill in between leaves a consistent series.
    """
    merge_time_collections(path)
    tree = parse_xdmf(path)
    late = [(c, g) for c in tree.getroot().iter("Grid") for g in c.findall("Grid")
            if float(_step_key(g)) > t + 1e-12 * max(1.0, abs(t))]
    for collection, grid in late:
        collection.remove(grid)
    kept = {ref for g in tree.getroot().iter("Grid") for ref in _references(g)}
    dropped = {ref for _, g in late for ref in _references(g)} - kept
    write_xml_atomic(tree, path)
    own = path.with_suffix(".h5").name
    for name in {f for f, _ in dropped} - {f for f, _ in kept} - {own}:
        (path.parent / name).unlink(missing_ok=True)
    _delete_datasets(path.with_suffix(".h5"), [d for f, d in dropped if f == own])


def _delete_datasets(h5_path: Path, datasets: list[str]) -> None:
    """Remove datasets from an HDF5 file through a copy and an atomic rename."""
    if not datasets:
        return
    tmp = h5_path.with_name(f".{h5_path.name}.tmp")
    shutil.copyfile(h5_path, tmp)
    with h5py.File(tmp, "a") as h5:
        for name in datasets:
            if name in h5:
                del h5[name]
    os.replace(tmp, h5_path)


def _references(grid: ET.Element) -> list[tuple[str, str]]:
    """``(file, dataset)`` pairs of the HDF ``DataItem`` s of a grid (``file.h5:/path``)."""
    return [(a.strip(), b.strip()) for a, _, b in
            (item.text.partition(":") for item in grid.iter("DataItem")
             if item.text and ":" in item.text)]


def complete_steps(path: Path) -> list[float]:
    """Return the times of the steps whose HDF5 datasets are all readable.

    A reader's fallback after a crash: a step whose data is missing or unreadable (or an
    unreadable XML file altogether) is left out instead of failing the whole series.
    """
    try:
        grids = [g for c in parse_xdmf(path).getroot().iter("Grid") for g in c.findall("Grid")]
    except (OSError, ET.ParseError):
        return []
    return [float(_step_key(g)) for g in grids if _readable(path.parent, _references(g))]


def _readable(folder: Path, refs: list[tuple[str, str]]) -> bool:
    """Whether every ``(file, dataset)`` exists and reads as finite numbers."""
    try:
        for name, dataset in refs:
            with h5py.File(folder / name, "r") as h5:
                if dataset not in h5 or not np.all(np.isfinite(h5[dataset][...])):
                    return False
        return True
    except (OSError, KeyError, TypeError):
        return False


ET.register_namespace("xi", XI[1:-1])


# --------------------------------------------------------------------------------------------
# Summary JSON


@functools.cache
def package_versions() -> dict[str, str]:
    """Versions of Python, PETSc, dolfinx and the scientific packages (computed once per run)."""
    versions = {"wrinkles": wrinkles_version(), "python": platform.python_version(),
                "dolfinx": dolfinx.__version__,
                "petsc": ".".join(str(v) for v in PETSc.Sys.getVersion()),
                "petsc4py": str(getattr(sys.modules.get("petsc4py"), "__version__", "?")),
                "mpi": MPI.Get_library_version().splitlines()[0].strip()}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


NON_FINITE: dict[str, float] = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}
"""How strict JSON spells the non-finite floats (strings; the scene loader reads them back)."""


def strict(data: Any) -> Any:
    """Return ``data`` with every non-finite float as the string ``"inf"``, ``"-inf"`` or ``"nan"``.

    Standard JSON has no ``Infinity`` / ``NaN`` tokens (Python writes them, most readers
    refuse them); numpy scalars become Python numbers on the way.
    """
    if isinstance(data, Mapping):
        return {str(k): strict(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [strict(v) for v in data]
    if isinstance(data, np.generic):
        data = data.item()
    if isinstance(data, float) and not math.isfinite(data):
        return "nan" if math.isnan(data) else ("inf" if data > 0 else "-inf")
    return data


def json_text(data: Any) -> str:
    """Return strict JSON text of ``data`` (:func:`strict`), compactly indented.

    Top-level entries are indented, items of top-level lists one line each.

    ``json.dumps`` with ``indent`` runs the pure-Python encoder; compact items use the C
    encoder, so rewriting ``summary.json`` after every frame stays cheap for long runs.
    """
    data = strict(data)
    if not isinstance(data, dict):
        return json.dumps(data, indent=2, allow_nan=False) + "\n"
    parts = []
    for key, value in data.items():
        if isinstance(value, list) and value:
            items = ",\n".join("    " + json.dumps(item, allow_nan=False) for item in value)
            text = "[\n" + items + "\n  ]"
        else:
            text = json.dumps(value, indent=2, allow_nan=False).replace("\n", "\n  ")
        parts.append(f"  {json.dumps(str(key))}: {text}")
    return "{\n" + ",\n".join(parts) + "\n}\n"


def write_json_atomic(path: Path, data: Any) -> None:
    """Write ``data`` as JSON (:func:`json_text`) to ``path`` atomically (tmp + ``os.replace``)."""
    write_text_atomic(path, json_text(data))


def summary_document(scene: Mapping[str, Any], run: Mapping[str, Any],
                     frames: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Assemble the summary: scene, versions, run facts and frame records (JSON-able)."""
    return {"scene": dict(scene), "versions": dict(package_versions()), "run": dict(run),
            "frames": [dict(f) for f in frames]}


# --------------------------------------------------------------------------------------------
# Divergence diagnostic


def worst_cell(body: Any) -> dict[str, Any]:
    """Locate the smallest ``det F`` over the body's volume quadrature points (collective).

    ``det F = det(I + grad u)`` at the degree-``qdegree`` points of every owned cell comes
    from :meth:`solvers.body.Body.det_f_points` (the expression of ``min_det_f``); the global
    minimum, its cell (global index), quadrature point and the cell's reference centroid are
    returned on every rank.
    """
    mesh = body.mesh
    imap = mesh.topology.index_map(mesh.topology.dim)
    values = body.det_f_points()
    local = (np.inf, -1, -1, [math.nan] * 3)
    if values.size:
        cell, point = np.unravel_index(int(np.argmin(values)), values.shape)
        centroid = mesh.geometry.x[mesh.geometry.dofmaps[0][cell]].mean(axis=0)
        local = (float(values[cell, point]), int(imap.local_to_global(np.array([cell]))[0]),
                 int(point), [float(c) for c in centroid])
    best = min(mesh.comm.allgather(local), key=lambda item: item[0])
    return {"min_det_f": best[0], "cell": best[1], "quadrature_point": best[2],
            "cell_centroid": best[3]}


def failure_diagnostic(body: Any, error: str) -> dict[str, Any]:
    """Collect what a user needs after a failed solve (collective).

    The body is in its last good state (``Body.step`` restores it on failure): its worst
    ``det F`` location, its energy terms with the dominant one, and the parameters of the
    material, the time integration and the Newton solver; ``error`` is the solver's message.
    """
    energies = body.energies()
    terms = {k: v for k, v in energies.items() if k != "total"}
    material = body.material
    return {"error": error, "time": body.t, "worst_det_f": worst_cell(body),
            "energies": energies, "dominant_energy": max(terms, key=lambda k: abs(terms[k])),
            "parameters": {"model": material.model, "E": material.E, "nu": material.nu,
                           "density": material.density, "dt": body.options.dt,
                           "dynamics": body.options.dynamics, "degree": body.options.degree,
                           "newton_max_it": body.newton.max_it,
                           "max_halvings": body.newton.max_halvings}}


def one_line(message: str) -> str:
    """Collapse a message to one line for stderr."""
    return " ".join(message.split())


def short_diagnostic(diagnostic: dict[str, Any]) -> str:
    """One-line form of :func:`failure_diagnostic`'s record."""
    worst, params = diagnostic["worst_det_f"], diagnostic["parameters"]
    centroid = ", ".join(f"{c:.4g}" for c in worst["cell_centroid"])
    energy = diagnostic["energies"][diagnostic["dominant_energy"]]
    return (f"last good state t={diagnostic['time']:.6g}: smallest det F={worst['min_det_f']:.4g} "
            f"in cell {worst['cell']} (quadrature point {worst['quadrature_point']}, "
            f"centroid ({centroid}) m), dominant energy term {diagnostic['dominant_energy']}="
            f"{energy:.4e} J, parameters " + ", ".join(f"{k}={v}" for k, v in params.items()))
