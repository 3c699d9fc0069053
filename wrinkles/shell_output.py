"""The shell's XDMF/HDF5 time series ``shell.xdmf`` + ``shell.h5`` (rank 0, h5py + XML).

The shell lives on every rank as plain numpy arrays (it is not a dolfinx mesh), so it is
written by rank 0 with h5py: the rest mesh once (``/Mesh/geometry`` (n, 3) float64,
``/Mesh/topology`` (m, 3) int64, ``/Mesh/cluster_id`` (n,) int64, the cluster partition), then
step ``k`` in its own file ``shell.steps/step_<k>.h5`` (:func:`wrinkles.output.step_file`):
``/displacement`` (n, 3) = x - rest, ``/bending_energy_density`` (n,) [J/m^2] and
``/self_intersecting`` (n,) (1 on the faces passing through another face, absent from series
written before it; :meth:`wrinkles.shell_setup.Shell.intersecting_faces`). A step is
written to ``.work/`` and moved to its place by ``os.replace``, then the XML is rewritten
through a temporary file + ``os.replace`` (the body series does the same), so a run killed at
any moment keeps every completed frame readable, and a frame costs O(its own size) in HDF5
bytes (older series with every step in ``shell.h5`` as ``/Step_<k>/...`` are still read and
resumed). On ``--resume`` the steps after
the checkpoint are dropped (:func:`wrinkles.output.drop_steps_after`) and the rerun frames
replace them.
The XML is XDMF 3: one temporal collection of uniform
grids, each referencing the one stored mesh and carrying the step's ``Time`` and its node
attributes; ParaView and ``meshio.xdmf.TimeSeriesReader`` read it.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import h5py
import numpy as np

from meshes.errors import InputError
from models.backend import MPI
from wrinkles.collective import on_root
from wrinkles.output import (
    WORK_DIR,
    XI,
    XML_HEADER,
    drop_steps_after,
    parse_xdmf,
    step_file,
    write_text_atomic,
)

if TYPE_CHECKING:
    from wrinkles.shell_setup import Shell

SHELL_XDMF_NAME = "shell.xdmf"
FIELD_TYPES: dict[str, str] = {"bending_energy_density": "Scalar", "displacement": "Vector",
                               "self_intersecting": "Scalar"}
"""Point fields of a step and their XDMF attribute type (the bending energy density first:
ParaView colours by the first scalar it finds)."""


@dataclass(frozen=True)
class ShellFrame:
    """One stored step of the shell series.

    Attributes:
        time: physical time [s].
        displacement: ``(n, 3)`` shell positions minus rest positions [m].
        bending_energy_density: ``(n,)`` per-vertex bending energy density [J/m^2].
        self_intersecting: ``(n,)`` 1.0 at the vertices of the faces that pass through
            another face, else 0.0; None where a series written before it has none.

    """

    time: float
    displacement: np.ndarray
    bending_energy_density: np.ndarray
    self_intersecting: np.ndarray | None = None

    def fields(self) -> dict[str, np.ndarray]:
        """Return the stored point fields by name, in :data:`FIELD_TYPES` order (None left out)."""
        return {name: np.asarray(getattr(self, name), dtype=np.float64) for name in FIELD_TYPES
                if getattr(self, name) is not None}


def _item(parent: ET.Element, h5_name: str, path: str, shape: tuple[int, ...],
          number: str) -> ET.Element:
    """Append an HDF ``DataItem`` pointing at ``h5_name:path``."""
    precision = "8"
    item = ET.SubElement(parent, "DataItem", Dimensions=" ".join(map(str, shape)),
                         Format="HDF", NumberType=number, Precision=precision)
    item.text = f"{h5_name}:{path}"
    return item


class ShellSeries:
    """Writer of the shell time series (call its methods on rank 0 only).

    Args:
        path: the ``.xdmf`` file; the mesh's ``.h5`` file and ``.steps/`` go beside it.
        rest: ``(n, 3)`` rest positions of the shell.
        faces: ``(m, 3)`` triangles.
        cluster_id: ``(n,)`` cluster of each vertex (nearest centre).
        resume_after: ``None`` to start a new series; for a restart, the time [s] of the
            restored state: the existing series is kept without its steps after that time.

    Raises:
        InputError: (resume) no series in ``path``, or its rest mesh is another one.

    """

    def __init__(self, path: Path, rest: np.ndarray, faces: np.ndarray,
                 cluster_id: np.ndarray, resume_after: float | None = None,
                 ) -> None:
        self.path, self.h5_path = path, path.with_suffix(".h5")
        self.work = path.parent / WORK_DIR / "shell_step.h5"
        self.n, self.m = rest.shape[0], faces.shape[0]
        self.times: list[float] = []
        self.sources: list[tuple[str, str]] = []
        self.fields: list[tuple[str, ...]] = []
        self._grids: list[str] = []
        if resume_after is not None:
            self._resume(np.asarray(rest, dtype=np.float64), resume_after)
            return
        self.work.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(self.work, "w") as h5:
            h5["Mesh/geometry"] = np.asarray(rest, dtype=np.float64)
            h5["Mesh/topology"] = np.asarray(faces, dtype=np.int64)
            h5["Mesh/cluster_id"] = np.asarray(cluster_id, dtype=np.int64)
        os.replace(self.work, self.h5_path)
        self._write_xml()

    def _resume(self, rest: np.ndarray, t: float) -> None:
        """Take over an existing series, dropping its steps after time ``t`` [s]."""
        if not (self.path.is_file() and self.h5_path.is_file()):
            raise InputError(f"{self.path}: no shell series to continue")
        with h5py.File(self.h5_path, "r") as h5:
            stored = h5["Mesh/geometry"][...]
        if stored.shape != rest.shape or not np.array_equal(stored, rest):
            raise InputError(f"{self.path}: its rest mesh differs from this scene's shell")
        drop_steps_after(self.path, t)
        steps = _steps(self.path)
        self.times = [time for time, _, _ in steps]
        self.sources = [source for _, source, _ in steps]
        self.fields = [names for _, _, names in steps]
        self._write_xml()

    def write(self, frame: ShellFrame) -> None:
        """Write one step into its own HDF5 file (work file + rename), then the XML."""
        dest = step_file(self.path, len(self.times))
        self.work.parent.mkdir(parents=True, exist_ok=True)
        fields = frame.fields()
        with h5py.File(self.work, "w") as h5:
            for name, values in fields.items():
                h5[name] = values
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(self.work, dest)
        self.times.append(float(frame.time))
        self.fields.append(tuple(fields))
        self.sources.append((dest.relative_to(self.path.parent).as_posix(), ""))
        self._write_xml()

    def _grid(self, index: int) -> str:
        """One uniform grid as XML text: the stored mesh, the step's time and attributes."""
        h5 = self.h5_path.name
        grid = ET.Element("Grid", Name=f"step_{index}", GridType="Uniform")
        topo = ET.SubElement(grid, "Topology", TopologyType="Triangle",
                             NumberOfElements=str(self.m), NodesPerElement="3")
        _item(topo, h5, "/Mesh/topology", (self.m, 3), "Int")
        geo = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
        _item(geo, h5, "/Mesh/geometry", (self.n, 3), "Float")
        ET.SubElement(grid, "Time", Value=repr(self.times[index]))
        source, prefix = self.sources[index]
        for name, kind in FIELD_TYPES.items():
            if name not in self.fields[index]:
                continue
            attr = ET.SubElement(grid, "Attribute", Name=name, AttributeType=kind, Center="Node")
            shape = (self.n, 3) if kind == "Vector" else (self.n,)
            _item(attr, source, f"{prefix}/{name}", shape, "Float")
        cid = ET.SubElement(grid, "Attribute", Name="cluster_id", AttributeType="Scalar",
                            Center="Node")  # colours by the first scalar it finds
        _item(cid, h5, "/Mesh/cluster_id", (self.n,), "Int")
        ET.indent(grid, "  ", level=3)
        return "      " + ET.tostring(grid, encoding="unicode").rstrip() + "\n"

    def _write_xml(self) -> None:
        """Rewrite the XML (all steps so far) atomically.

        The text of the steps already written is kept (``_grids``), so a frame serialises
        only its own grid and writes the concatenation (about 1 kB per step).
        """
        self._grids.extend(self._grid(k) for k in range(len(self._grids), len(self.times)))
        text = (f'{XML_HEADER}<Xdmf Version="3.0" xmlns:xi="{XI[1:-1]}">\n  <Domain>\n'
                '    <Grid Name="shell" GridType="Collection" CollectionType="Temporal">\n'
                + "".join(self._grids) + "    </Grid>\n  </Domain>\n</Xdmf>\n")
        write_text_atomic(self.path, text)


def _steps(path: Path) -> list[tuple[float, tuple[str, str], tuple[str, ...]]]:
    """Return each step of a shell series (its XML): time, ``(file, group)``, field names."""
    steps = []
    for grid in parse_xdmf(path).getroot().iter("Grid"):
        time = grid.find("Time")
        item = grid.find("Attribute[@Name='displacement']/DataItem")
        if time is None or item is None or not item.text:
            continue
        name, _, dataset = item.text.partition(":")
        fields = tuple(attr.get("Name", "") for attr in grid.iter("Attribute")
                       if attr.get("Name") in FIELD_TYPES)
        steps.append((float(time.get("Value", "0")),
                      (name.strip(), dataset.strip().rsplit("/", 1)[0]), fields))
    return steps


def step_sources(path: Path) -> tuple[list[float], list[tuple[str, str]]]:
    """Return the times and ``(file, group)`` of the steps of a shell series (its XML).

    ``group`` is the HDF5 group holding the step's fields in ``file`` (``""`` for per-step
    files, ``/Step_<k>`` for series written before them).
    """
    steps = _steps(path)
    return [time for time, _, _ in steps], [source for _, source, _ in steps]


def read_shell_series(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                           list[ShellFrame]]:
    """Read a shell series back: ``(rest, faces, cluster_id, frames)`` (h5py + the XML).

    Raises:
        FileNotFoundError: no such series.

    """
    times, sources = step_sources(path)
    with h5py.File(path.with_suffix(".h5"), "r") as h5:
        rest, faces = h5["Mesh/geometry"][...], h5["Mesh/topology"][...]
        cluster_id = h5["Mesh/cluster_id"][...]
    frames = []
    for t, (name, group) in zip(times, sources, strict=True):
        with h5py.File(path.parent / name, "r") as h5:
            crossing = (h5[f"{group}/self_intersecting"][...]
                        if f"{group}/self_intersecting" in h5 else None)
            frames.append(ShellFrame(t, h5[f"{group}/displacement"][...],
                                     h5[f"{group}/bending_energy_density"][...], crossing))
    return rest, faces, cluster_id, frames


__all__ = ["SHELL_XDMF_NAME", "ShellFrame", "ShellSeries", "Writer", "make_writer",
           "read_shell_series", "shell_frame", "step_sources"]


Writer = Callable[[int, float], None]
"""``write(frame, t)``: append the shell's current state to its series (when the frame is due)."""


def shell_frame(shell: Shell, t: float) -> ShellFrame:
    """Return the output fields of the current state."""
    from models.shell.self_intersection import vertex_flags  # numba: a writer's, not a reader's

    crossing = vertex_flags(shell.topology.faces, shell.intersecting_faces(), shell.rest.shape[0])
    return ShellFrame(t, shell.x - shell.rest, shell.energy.bending_density(shell.x), crossing)


def make_writer(shell: Shell, out: Path, comm: MPI.Comm, writes: Callable[[int], bool],
                resume_after: float | None = None) -> Writer:
    """Create ``shell.xdmf`` with the rest state (t = 0); return ``write(frame, t)``.

    With ``resume_after`` (time [s] of the restored state) the existing series is continued
    instead, without its steps after that time (collective: errors are raised on all ranks).
    """
    path, faces, cid = out / SHELL_XDMF_NAME, shell.topology.faces, shell.clusters.partition
    series = on_root(comm, lambda: ShellSeries(path, shell.rest, faces, cid, resume_after))
    if series is not None and resume_after is None:
        series.write(shell_frame(shell, 0.0))

    def write(frame: int, t: float) -> None:
        if series is not None and writes(frame):
            series.write(shell_frame(shell, t))

    return write
