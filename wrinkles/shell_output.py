"""The shell's XDMF/HDF5 time series ``shell.xdmf`` + ``shell.h5`` (rank 0, h5py + XML).

The shell lives on every rank as plain numpy arrays (it is not a dolfinx mesh), so it is
written by rank 0 with h5py: the rest mesh once (``/Mesh/geometry`` (n, 3) float64,
``/Mesh/topology`` (m, 3) int64, ``/Mesh/cluster_id`` (n,) int64, the cluster partition), then
per step ``/Step_<k>/displacement`` (n, 3) = x - rest and
``/Step_<k>/bending_energy_density`` (n,) [J/m^2]. Each step is written through the same
kill-safe transaction as the body series (:func:`wrinkles.output.begin_frame` /
:func:`wrinkles.output.commit_frame`: copy to ``.work/``, append, atomic rename of the HDF5
file, then the XML through a temporary file + ``os.replace``), so a run killed at any moment
keeps every completed frame readable. On ``--resume`` the steps after the checkpoint are
dropped (:func:`wrinkles.output.drop_steps_after`) and the rerun frames replace them.
The XML is XDMF 3: one temporal collection of uniform
grids, each referencing the one stored mesh and carrying the step's ``Time`` and its three
node attributes; ParaView and ``meshio.xdmf.TimeSeriesReader`` read it.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from models.errors import InputError
from wrinkles.output import (
    WORK_DIR,
    begin_frame,
    commit_frame,
    drop_steps_after,
    write_xml_atomic,
)

SHELL_XDMF_NAME = "shell.xdmf"
FIELD_TYPES: dict[str, str] = {"displacement": "Vector", "bending_energy_density": "Scalar"}
"""Point fields of every step and their XDMF attribute type."""


@dataclass(frozen=True)
class ShellFrame:
    """One stored step of the shell series.

    Attributes:
        time: physical time [s].
        displacement: ``(n, 3)`` shell positions minus rest positions [m].
        bending_energy_density: ``(n,)`` per-vertex bending energy density [J/m^2].

    """

    time: float
    displacement: np.ndarray
    bending_energy_density: np.ndarray


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
        path: the ``.xdmf`` file; the ``.h5`` file goes beside it.
        rest: ``(n, 3)`` rest positions of the shell.
        faces: ``(m, 3)`` triangles.
        cluster_id: ``(n,)`` cluster of each vertex (nearest centre).
        resume_after: ``None`` to start a new series; for a restart, the time [s] of the
            restored state: the existing series is kept without its steps after that time.
        atomic: write each step as a kill-safe transaction (``OutputOptions.atomic``).

    Raises:
        InputError: (resume) no series in ``path``, or its rest mesh is another one.

    """

    def __init__(self, path: Path, rest: np.ndarray, faces: np.ndarray,
                 cluster_id: np.ndarray, resume_after: float | None = None,
                 atomic: bool = True) -> None:
        self.path, self.h5_path, self.atomic = path, path.with_suffix(".h5"), atomic
        self.work = path.parent / WORK_DIR / path.name
        self.n, self.m = rest.shape[0], faces.shape[0]
        self.times: list[float] = []
        if resume_after is not None:
            self._resume(np.asarray(rest, dtype=np.float64), resume_after)
            return
        with h5py.File(self.h5_path, "w") as h5:
            h5["Mesh/geometry"] = np.asarray(rest, dtype=np.float64)
            h5["Mesh/topology"] = np.asarray(faces, dtype=np.int64)
            h5["Mesh/cluster_id"] = np.asarray(cluster_id, dtype=np.int64)
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
        self.times = [float(x.get("Value", "0")) for x in ET.parse(self.path).iter("Time")]
        self._write_xml()

    def write(self, frame: ShellFrame) -> None:
        """Append one step: HDF5 data in a work copy, renamed over, then the XML."""
        step = f"Step_{len(self.times)}"
        target = begin_frame(self.path, self.work, self.atomic)
        with h5py.File(target.with_suffix(".h5"), "a") as h5:
            if step in h5:  # left by a kill between the HDF5 rename and the XML commit
                del h5[step]
            h5[f"{step}/displacement"] = np.asarray(frame.displacement, dtype=np.float64)
            h5[f"{step}/bending_energy_density"] = np.asarray(frame.bending_energy_density,
                                                              dtype=np.float64)
        self.times.append(float(frame.time))
        commit_frame(self.path, self.work, self.atomic, self._write_xml)

    def _grid(self, parent: ET.Element, index: int) -> None:
        """One uniform grid: the stored mesh, the step's time and attributes."""
        h5 = self.h5_path.name
        grid = ET.SubElement(parent, "Grid", Name=f"step_{index}", GridType="Uniform")
        topo = ET.SubElement(grid, "Topology", TopologyType="Triangle",
                             NumberOfElements=str(self.m), NodesPerElement="3")
        _item(topo, h5, "/Mesh/topology", (self.m, 3), "Int")
        geo = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
        _item(geo, h5, "/Mesh/geometry", (self.n, 3), "Float")
        ET.SubElement(grid, "Time", Value=repr(self.times[index]))
        cid = ET.SubElement(grid, "Attribute", Name="cluster_id", AttributeType="Scalar",
                            Center="Node")
        _item(cid, h5, "/Mesh/cluster_id", (self.n,), "Int")
        for name, kind in FIELD_TYPES.items():
            attr = ET.SubElement(grid, "Attribute", Name=name, AttributeType=kind, Center="Node")
            shape = (self.n, 3) if kind == "Vector" else (self.n,)
            _item(attr, h5, f"/Step_{index}/{name}", shape, "Float")

    def _write_xml(self) -> None:
        """Rewrite the XML (all steps so far) atomically."""
        root = ET.Element("Xdmf", Version="3.0")
        domain = ET.SubElement(root, "Domain")
        collection = ET.SubElement(domain, "Grid", Name="shell", GridType="Collection",
                                   CollectionType="Temporal")
        for index in range(len(self.times)):
            self._grid(collection, index)
        write_xml_atomic(ET.ElementTree(root), self.path)


def read_shell_series(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                           list[ShellFrame]]:
    """Read a shell series back: ``(rest, faces, cluster_id, frames)`` (h5py + the XML times).

    Raises:
        FileNotFoundError: no such series.

    """
    times = [float(t.get("Value", "0")) for t in ET.parse(path).getroot().iter("Time")]
    with h5py.File(path.with_suffix(".h5"), "r") as h5:
        rest, faces = h5["Mesh/geometry"][...], h5["Mesh/topology"][...]
        cluster_id = h5["Mesh/cluster_id"][...]
        frames = [ShellFrame(t, h5[f"Step_{k}/displacement"][...],
                             h5[f"Step_{k}/bending_energy_density"][...])
                  for k, t in enumerate(times)]
    return rest, faces, cluster_id, frames


__all__ = ["SHELL_XDMF_NAME", "ShellFrame", "ShellSeries", "read_shell_series"]
