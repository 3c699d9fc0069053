"""``wrinkles view RUN``: open a run in ParaView in one step, and a VTK XML (``.pvd``) export.

``RUN/view.py`` is a ParaView Python script: it loads ``body.xdmf`` and ``shell.xdmf`` (the
Xdmf3 reader), warps both by their ``displacement`` (the files store the rest shape), colours
the shell by ``bending_energy_density`` on a log scale with the range of the last step, marks
in magenta the faces passing through another face at the last step (``self_intersecting``),
shows the body as a translucent surface, the rigid balls of ``balls.xdmf`` as spheres of their
radius, and jumps to the last time step. Open it with ``paraview --script=RUN/view.py``, or
``pvpython RUN/view.py`` to write ``RUN/view.png`` without a window (on a machine without a
display, ``xvfb-run -a -s -noreset pvpython RUN/view.py``, :data:`HEADLESS`: a ParaView built
for on-screen rendering, as Debian's, needs an X server even for ``pvpython``).

``--pvd`` also writes ``RUN/vtk/{body,shell,balls}.pvd`` with one ``.vtu`` per step whose
points are already deformed (``displacement`` and the other fields kept as point data), for
tools without an XDMF reader (pyvista, VisIt, Blender importers).
"""

from __future__ import annotations

import argparse
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import meshio
import numpy as np

from meshes.errors import InputError
from wrinkles.output import XDMF_NAME, XML_HEADER, write_text_atomic
from wrinkles.render import CAMERAS, scene_up
from wrinkles.rigid_output import BALLS_XDMF_NAME, read_balls
from wrinkles.shell_output import SHELL_XDMF_NAME, read_shell_series

VIEW_SCRIPT = "view.py"
PVD_DIR = "vtk"

HEADLESS: tuple[str, ...] = ("xvfb-run", "-a", "-s", "-noreset", "pvpython")
"""The command prefix that runs ``view.py`` without a display: a virtual X server that does not
reset. By default Xvfb resets when its last client disconnects and drops a client connecting
meanwhile; ``pvpython`` closes its first connection and opens another, which then fails
("bad X server connection", SIGABRT) in a third to a half of the runs on a 2-core machine
(ParaView 5.11, Debian 12; docs/notes/paraview-headless.md). ``-s`` replaces xvfb-run's
default server arguments (an 8-bit screen) by Xvfb's own defaults (24-bit) and ``-noreset``."""

SCRIPT = '''"""ParaView view of a wrinkles run (written by `wrinkles view`).

    paraview --script={run}/view.py     # interactive
    pvpython {run}/view.py              # writes {run}/view.png
    xvfb-run -a -s -noreset pvpython {run}/view.py  # the same without a display
"""
import os
from paraview.simple import *  # noqa: F403

RUN = os.path.dirname(os.path.abspath(__file__))
view = GetActiveViewOrCreate("RenderView")


def warped(name):
    path = os.path.join(RUN, name)
    if not os.path.exists(path):
        return None
    reader = Xdmf3ReaderS(registrationName=name, FileName=[path])
    warp = WarpByVector(registrationName=name + " (deformed)", Input=reader)
    warp.Vectors = ["POINTS", "displacement"]
    return warp


scene = GetAnimationScene()
scene.UpdateAnimationUsingDataTimeSteps()
body = warped("body.xdmf")
if body is not None:
    shown = Show(body, view)
    shown.Opacity = 0.25
    shown.ColorArrayName = ["POINTS", ""]
shell = warped("shell.xdmf")
if shell is not None:
    shown = Show(shell, view)
    ColorBy(shown, ("POINTS", "bending_energy_density"))
    lut = GetColorTransferFunction("bending_energy_density")
    scene.UpdateAnimationUsingDataTimeSteps()
    scene.AnimationTime = scene.EndTime
    values = shell.PointData["bending_energy_density"].GetRange()
    lut.RescaleTransferFunction(max(values[1] * 1e-4, 1e-30), max(values[1], 1e-29))
    lut.UseLogScale = 1
    shown.SetScalarBarVisibility(view, True)
    bar = GetScalarBar(lut, view)
    bar.DrawTickLabels = 0
    bar.Title = "bending energy density"
    bar.ComponentTitle = "[J/m^2]"
    bar.HorizontalTitle = 1
    bar.TitleFontSize = 14
    bar.LabelFontSize = 12
    bar.ScalarBarLength = 0.4
    bar.WindowLocation = "Lower Right Corner"
    names = shell.PointData.keys()
    if "self_intersecting" in names and shell.PointData["self_intersecting"].GetRange()[1] > 0:
        faces = Threshold(registrationName="self-intersecting faces", Input=shell)
        faces.Scalars = ["POINTS", "self_intersecting"]
        faces.LowerThreshold, faces.UpperThreshold = 0.5, 1.0
        marked = Show(faces, view)
        marked.ColorArrayName = ["POINTS", ""]
        marked.DiffuseColor = [1.0, 0.0, 1.0]
        marked.Representation = "Surface With Edges"
        print("self-intersecting faces at the last step: shown in magenta")
balls_path = os.path.join(RUN, "balls.xdmf")
if os.path.exists(balls_path):
    balls = Xdmf3ReaderS(registrationName="balls.xdmf", FileName=[balls_path])
    glyph = Glyph(registrationName="balls", Input=balls, GlyphType="Sphere")
    glyph.ScaleArray = ["POINTS", "radius"]
    glyph.ScaleFactor = 2.0
    glyph.GlyphType.ThetaResolution = 32
    glyph.GlyphType.PhiResolution = 32
    glyph.GlyphMode = "All Points"
    shown = Show(glyph, view)
    shown.ColorArrayName = ["POINTS", ""]
    shown.DiffuseColor = [0.7, 0.13, 0.13]
scene.UpdateAnimationUsingDataTimeSteps()
scene.AnimationTime = scene.EndTime
view.CameraFocalPoint = [0.0, 0.0, 0.0]
view.CameraPosition = {direction}
view.CameraViewUp = {view_up}
view.ResetCamera()
Render()
SaveScreenshot(os.path.join(RUN, "view.png"), view, ImageResolution=[1280, 800],
               FontScaling="Do not scale fonts")
'''


def write_view_script(run: Path) -> Path:
    """Write ``run/view.py`` (module docstring); return its path.

    Raises:
        InputError: ``run`` holds neither ``body.xdmf`` nor ``shell.xdmf``.

    """
    if not (run / XDMF_NAME).is_file() and not (run / SHELL_XDMF_NAME).is_file():
        raise InputError(f"{run}: no body.xdmf or shell.xdmf (is it the output directory of a "
                         f"run with output.xdmf = true?)")
    path = run / VIEW_SCRIPT
    direction, view_up = CAMERAS[scene_up(run)]
    text = (SCRIPT.replace("{run}", str(run)).replace("{direction}", str(list(direction)))
            .replace("{view_up}", str(list(view_up))))
    write_text_atomic(path, text)
    return path


def write_pvd(path: Path, entries: list[tuple[float, str]]) -> None:
    """Write a ParaView collection file listing ``(time, file)`` datasets."""
    root = ET.Element("VTKFile", type="Collection", version="0.1")
    collection = ET.SubElement(root, "Collection")
    for time, name in entries:
        ET.SubElement(collection, "DataSet", timestep=repr(time), part="0", file=name)
    ET.indent(root, "  ")
    write_text_atomic(path, XML_HEADER + ET.tostring(root, encoding="unicode") + "\n")


def export_body(run: Path, folder: Path) -> Path | None:
    """``body.pvd``: the body's tets per step, points moved by the displacement."""
    source = run / XDMF_NAME
    if not source.is_file():
        return None
    entries = []
    with meshio.xdmf.TimeSeriesReader(str(source)) as reader:
        points, cells = reader.read_points_cells()
        for k in range(reader.num_steps):
            t, data, _ = reader.read_data(k)
            name = f"body_{k:04d}.vtu"
            moved = points + data["displacement"]
            meshio.write(folder / name, meshio.Mesh(moved, cells, point_data=data))
            entries.append((float(t), name))
    write_pvd(folder / "body.pvd", entries)
    return folder / "body.pvd"


def export_shell(run: Path, folder: Path) -> Path | None:
    """``shell.pvd``: the shell's triangles per step, points moved by the displacement."""
    source = run / SHELL_XDMF_NAME
    if not source.is_file():
        return None
    rest, faces, cluster, frames = read_shell_series(source)
    entries = []
    for k, frame in enumerate(frames):
        name = f"shell_{k:04d}.vtu"
        data: dict[str, Any] = {**frame.fields(), "cluster_id": np.asarray(cluster)}
        meshio.write(folder / name, meshio.Mesh(rest + frame.displacement, [("triangle", faces)],
                                                point_data=data))
        entries.append((frame.time, name))
    write_pvd(folder / "shell.pvd", entries)
    return folder / "shell.pvd"


def export_balls(run: Path, folder: Path) -> Path | None:
    """``balls.pvd``: the ball centres per step as vertices with ``radius`` and ``velocity``."""
    source = run / BALLS_XDMF_NAME
    if not source.is_file():
        return None
    radii, steps = read_balls(source)
    entries = []
    for k, step in enumerate(steps):
        name = f"balls_{k:04d}.vtu"
        vertices = [("vertex", np.arange(radii.size).reshape(-1, 1))]
        meshio.write(folder / name, meshio.Mesh(step.centers, vertices, point_data={
            "radius": radii, "velocity": step.velocities}))
        entries.append((step.time, name))
    write_pvd(folder / "balls.pvd", entries)
    return folder / "balls.pvd"


def export_pvd(run: Path) -> list[Path]:
    """Write ``run/vtk/*.pvd`` and their ``.vtu`` files; return the ``.pvd`` paths."""
    folder = run / PVD_DIR
    folder.mkdir(exist_ok=True)
    written = [export(run, folder) for export in (export_body, export_shell, export_balls)]
    return [path for path in written if path is not None]


def add_parser(commands: Any) -> Any:
    """Add the ``view`` sub-command to an argparse sub-parser collection; return it."""
    parser = commands.add_parser("view", help="write RUN/view.py, a ParaView script showing "
                                 "the deformed body, shell and balls (paraview --script=...)")
    parser.add_argument("out", type=Path, help="output directory of a run")
    parser.add_argument("--pvd", action="store_true",
                        help="also export RUN/vtk/*.pvd (VTK XML, points already deformed)")
    return parser


def command_view(args: argparse.Namespace) -> int:
    """Run the ``view`` sub-command; return the exit code."""
    script = write_view_script(args.out)
    print(f"wrote {script}: open it with  paraview --script={script}  (or pvpython {script} "
          f"for {args.out / 'view.png'}; without a display: {' '.join(HEADLESS)} {script})",
          flush=True)
    if args.pvd:
        for path in export_pvd(args.out):
            print(f"wrote {path}", flush=True)
    return 0
