"""The rigid balls' time series ``balls.xdmf``: centres, radii and velocities per frame.

One XDMF 3 temporal collection of ``Polyvertex`` grids with the data inline (a few numbers
per ball and frame, no HDF5 file): point ``i`` of a step is ball ``i``'s centre [m], with the
point fields ``radius`` [m] and ``velocity`` [m/s]. In ParaView a ``Glyph`` filter with a
sphere source scaled by ``radius`` shows the balls beside ``body.xdmf`` and ``shell.xdmf``
(``wrinkles view`` sets that up); ``wrinkles render`` draws them as spheres. The file is
rebuilt from the run's frame records after every frame (t = 0 from the scene), so a resumed
run rewrites it consistently, and replaced atomically.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meshes.errors import InputError
from wrinkles.output import XML_HEADER, write_text_atomic

BALLS_XDMF_NAME = "balls.xdmf"


@dataclass(frozen=True)
class BallStep:
    """The balls at one output time.

    Attributes:
        time: physical time [s].
        centers: ``(N, 3)`` centres [m].
        velocities: ``(N, 3)`` velocities [m/s].

    """

    time: float
    centers: np.ndarray
    velocities: np.ndarray


def ball_steps(initial: BallStep, records: Sequence[Any]) -> list[BallStep]:
    """Return the initial state and one step per frame record with ``details["balls"]``."""
    steps = [initial]
    for record in records:
        balls = getattr(record, "details", {}).get("balls")
        if balls:
            steps.append(BallStep(float(record.time),
                                  np.array([b["center"] for b in balls], dtype=float),
                                  np.array([b["velocity"] for b in balls], dtype=float)))
    return steps


def _item(parent: ET.Element, values: np.ndarray, number: str = "Float") -> None:
    """Append an inline ``DataItem`` holding ``values``."""
    item = ET.SubElement(parent, "DataItem", Dimensions=" ".join(map(str, values.shape)),
                         NumberType=number, Precision="8" if number == "Float" else "4",
                         Format="XML")
    item.text = " ".join(repr(float(v)) if number == "Float" else str(int(v))
                         for v in values.ravel())


def balls_xml(steps: Sequence[BallStep], radii: np.ndarray) -> str:
    """XDMF text of the ball series (module docstring)."""
    root = ET.Element("Xdmf", Version="3.0")
    collection = ET.SubElement(ET.SubElement(root, "Domain"), "Grid", Name="balls",
                               GridType="Collection", CollectionType="Temporal")
    n = radii.size
    for k, step in enumerate(steps):
        grid = ET.SubElement(collection, "Grid", Name=f"step_{k}", GridType="Uniform")
        ET.SubElement(grid, "Time", Value=repr(step.time))
        topology = ET.SubElement(grid, "Topology", TopologyType="Polyvertex",
                                 NumberOfElements=str(n), NodesPerElement="1")
        _item(topology, np.arange(n).reshape(n, 1), "Int")
        _item(ET.SubElement(grid, "Geometry", GeometryType="XYZ"), step.centers.reshape(n, 3))
        for name, kind, values in (("radius", "Scalar", radii),
                                   ("velocity", "Vector", step.velocities.reshape(n, 3))):
            attribute = ET.SubElement(grid, "Attribute", Name=name, AttributeType=kind,
                                      Center="Node")
            _item(attribute, values)
    ET.indent(root, "  ")
    return XML_HEADER + ET.tostring(root, encoding="unicode") + "\n"


def write_balls(path: Path, steps: Sequence[BallStep], radii: np.ndarray) -> None:
    """Write the ball series to ``path`` atomically (rank 0)."""
    write_text_atomic(path, balls_xml(steps, np.asarray(radii, dtype=float)))


def read_balls(path: Path) -> tuple[np.ndarray, list[BallStep]]:
    """Return ``(radii, steps)`` of a ``balls.xdmf`` written by :func:`write_balls`.

    Raises:
        InputError: the file is missing or not such a series.

    """
    try:
        root = ET.parse(path).getroot()
        radii: np.ndarray = np.zeros(0)
        steps = []
        for grid in root.iter("Grid"):
            if grid.get("GridType") != "Uniform":
                continue
            data = {a.get("Name"): _values(a) for a in grid.findall("Attribute")}
            geometry, time = grid.find("Geometry"), grid.find("Time")
            if geometry is None or time is None:
                raise ValueError("a step without Geometry or Time")
            radii = data["radius"]
            steps.append(BallStep(float(time.get("Value", "nan")),
                                  _values(geometry).reshape(-1, 3),
                                  data["velocity"].reshape(-1, 3)))
    except (OSError, ET.ParseError, KeyError, AttributeError, ValueError) as exc:
        raise InputError(f"{path}: not a ball series ({exc})") from None
    return radii, steps


def _values(element: ET.Element) -> np.ndarray:
    """Numbers of the inline ``DataItem`` under ``element``."""
    item = element.find("DataItem")
    if item is None or item.text is None:
        raise ValueError(f"no data under {element.tag}")
    return np.array(item.text.split(), dtype=float)


__all__ = ["BALLS_XDMF_NAME", "BallStep", "ball_steps", "balls_xml", "read_balls", "write_balls"]
