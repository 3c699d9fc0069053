"""Off-screen pictures of the shell: PNG frames, ``shell.png`` (last frame) and ``shell.gif``.

``wrinkles render OUT_DIR`` (or ``python -m wrinkles.render OUT_DIR``) reads ``shell.xdmf`` /
``shell.h5`` of a run with h5py (pyvista cannot read the dolfinx/XDMF layout), builds a
pyvista ``PolyData`` of the deformed shell ``rest + displacement`` per stored step, coloured by
the bending energy density, and renders it off-screen. The colour range is fixed over all
frames (the 2nd-98th percentile of the density over all steps) so the animation does not
flicker; lighting with specular highlights makes wrinkles visible even where the density is
small. The GIF is assembled with Pillow.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meshes.errors import InputError
from wrinkles.rigid_output import BALLS_XDMF_NAME, read_balls
from wrinkles.shell_output import SHELL_XDMF_NAME, ShellFrame, read_shell_series


@dataclass(frozen=True)
class RenderOptions:
    """How the shell is rendered.

    Attributes:
        width: image width [px].
        height: image height [px].
        frames_dir: sub-directory of the run for the per-frame PNGs.
        gif_ms: duration of one GIF frame [ms].
        view: camera direction, a vector from the focal point towards the camera; ``None``
            looks from the side and above the scene's ``up`` axis (:data:`CAMERAS`).
        colormap: matplotlib colormap name for the bending energy density.
        log_scale: colour by log10 of the density (wrinkle crests stand out).
        up: the scene's up axis ("x", "y", "z"); ``None`` reads it from the run's summary.

    """

    width: int = 960
    height: int = 640
    frames_dir: str = "frames"
    gif_ms: int = 150
    view: tuple[float, float, float] | None = None
    colormap: str = "viridis"
    log_scale: bool = True
    up: str | None = None

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise InputError(f"render: width and height must be >= 16, got "
                             f"{self.width}x{self.height}")
        if self.gif_ms < 1:
            raise InputError(f"render.gif_ms: must be >= 1, got {self.gif_ms}")


CAMERAS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "z": ((1.0, -1.6, 1.1), (0.0, 0.0, 1.0)),
    "y": ((1.0, 1.1, 1.6), (0.0, 1.0, 0.0)),
    "x": ((1.1, 1.0, -1.6), (1.0, 0.0, 0.0)),
}
"""Scene ``up`` axis -> camera direction (towards the camera) and view-up vector."""


LOG_DECADES: float = 6.0
"""Decades of bending energy density a log-scale render shows at most."""


def scene_up(out: Path) -> str:
    """Return the ``up`` axis of the run in ``out`` (from its summary; "z" without one)."""
    try:
        up = json.loads((Path(out) / "summary.json").read_text())["scene"].get("up", "z")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return "z"
    return up if up in CAMERAS else "z"


CROSSING_COLOUR = "magenta"
"""Colour of the faces that pass through another face (as in ``wrinkles view`` and ``plot``;
in neither colour map)."""


def polydata(rest: np.ndarray, faces: np.ndarray, frame: ShellFrame) -> Any:
    """Return the deformed shell of one step as pyvista PolyData with its point fields."""
    import pyvista as pv

    cells = np.hstack([np.full((faces.shape[0], 1), 3), faces]).astype(np.int64).ravel()
    mesh = pv.PolyData(rest + frame.displacement, cells)
    for name, values in frame.fields().items():
        if name != "displacement":
            mesh.point_data[name] = values
    return mesh


def colour_values(density: np.ndarray, options: RenderOptions, floor: float) -> np.ndarray:
    """Return the scalars shown: the density, or log10 of it (values below ``floor`` raised)."""
    if not options.log_scale:
        return density
    return np.log10(np.maximum(density, floor))


def colour_range(frames: Sequence[ShellFrame], options: RenderOptions) -> tuple[float, float]:
    """Return the 2nd and 98th percentile of the shown scalars over all frames.

    In log scale only positive densities count (the rest state has none at all), and at most
    :data:`LOG_DECADES` decades below the upper end are shown (round-off-sized densities of a
    barely deformed region would stretch the map over 20 decades); the lower end is also the
    floor applied to smaller values.
    """
    values = np.concatenate([f.bending_energy_density for f in frames])
    if options.log_scale:
        values = np.log10(values[values > 0.0]) if np.any(values > 0.0) else np.zeros(1)
    lo, hi = np.percentile(values, [2.0, 98.0])
    if options.log_scale:
        lo = max(lo, hi - LOG_DECADES)
    return float(lo), float(max(hi, lo + 1e-12))


def render_frame(mesh: Any, path: Path, clim: tuple[float, float], options: RenderOptions,
                 camera: Any | None = None, balls: Any | None = None) -> Any:
    """Render a PolyData (and the balls' spheres) off-screen; return the camera (reuse it).

    Faces whose three vertices carry ``self_intersecting`` = 1 are drawn over it in
    :data:`CROSSING_COLOUR` with their edges.
    """
    plotter = offscreen_plotter(options)
    floor = 10.0 ** clim[0] if options.log_scale else 0.0
    scalars = colour_values(mesh.point_data["bending_energy_density"], options, floor)
    title = "log10 bending energy density" if options.log_scale else "bending energy density"
    plotter.add_mesh(mesh, scalars=scalars, clim=clim, cmap=options.colormap, smooth_shading=True,
                     specular=0.5, specular_power=20.0, scalar_bar_args={"title": title})
    crossing = mesh.point_data.get("self_intersecting")
    if crossing is not None and np.any(np.asarray(crossing) > 0.5):
        marked = mesh.threshold(0.5, scalars="self_intersecting", all_scalars=True)
        plotter.add_mesh(marked, color=CROSSING_COLOUR, show_edges=True)
    if balls is not None:
        plotter.add_mesh(balls, color="firebrick", smooth_shading=True, specular=0.6)
    if camera is None:
        aim(plotter, options)
    else:
        plotter.camera = camera
    plotter.screenshot(str(path))
    used = plotter.camera.copy()
    plotter.close()
    return used


def offscreen_plotter(options: RenderOptions) -> Any:
    """Return an off-screen pyvista plotter of the options' size."""
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkLogger

    # Without a display VTK falls back to off-screen rendering but first logs a warning ("bad X
    # server connection") that reads like an error; keep its stderr log to real errors.
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    return pv.Plotter(off_screen=True, window_size=[options.width, options.height])


def aim(plotter: Any, options: RenderOptions) -> None:
    """Point the plotter's camera along the view direction at everything it holds, zoomed."""
    direction, view_up = CAMERAS[options_up(options)]
    plotter.view_vector(options.view or direction, viewup=view_up)
    plotter.camera.zoom(1.2)


def view_camera(mesh: Any, options: RenderOptions, balls: Any | None = None) -> Any:
    """Return the camera :func:`render_frame` aims at ``mesh`` and ``balls`` (no picture).

    Every frame of a run is rendered with the camera of its first frame, which each rank of a
    parallel render computes alike.
    """
    plotter = offscreen_plotter(options)
    for item in (mesh, balls):
        if item is not None:
            plotter.add_mesh(item)
    aim(plotter, options)
    camera = plotter.camera.copy()
    plotter.close()
    return camera


def ball_spheres(path: Path) -> Callable[[float], Any | None]:
    """Return ``spheres(t)``: the balls nearest to time ``t`` as one mesh (or ``None``)."""
    import pyvista as pv

    if not path.is_file():
        return lambda t: None
    radii, steps = read_balls(path)
    times = np.array([s.time for s in steps])

    def spheres(t: float) -> Any:
        step = steps[int(np.argmin(np.abs(times - t)))]
        return pv.merge([pv.Sphere(radius=float(r), center=c, theta_resolution=48,
                                   phi_resolution=48) for r, c in zip(radii, step.centers,
                                                                      strict=True)])

    return spheres


def options_up(options: RenderOptions) -> str:
    """Return the up axis the camera stands on ("z" unless the options name another)."""
    return options.up if options.up in CAMERAS else "z"


def write_gif(pngs: Sequence[Path], path: Path, options: RenderOptions) -> None:
    """Assemble PNG frames into an animated GIF with Pillow (looping).

    Each frame gets its own 256-colour palette by Pillow's fast octree quantiser (the PNGs
    are the full-colour pictures; the GIF is their preview).
    """
    from PIL import Image

    images = [Image.open(p).convert("RGB").quantize(256, method=Image.Quantize.FASTOCTREE)
              for p in pngs]
    images[0].save(path, save_all=True, append_images=images[1:], duration=options.gif_ms,
                   loop=0)


def render_run(out: Path, options: RenderOptions | None = None,
               comm: Any | None = None) -> list[Path]:
    """Render every stored step of ``out/shell.xdmf``; return the files written.

    Writes ``out/frames/shell_NNNN.png``, ``out/shell.png`` (the last step) and
    ``out/shell.gif``. With an MPI ``comm`` (collective) rank ``r`` of ``p`` renders the steps
    ``r, r + p, ...`` with the same colour range and camera, and rank 0 writes ``shell.png``
    and the GIF once all are done and returns the files (the others an empty list).

    Raises:
        InputError: no shell series in ``out``.

    """
    opts = options or RenderOptions()
    if opts.up is None:
        opts = dataclasses.replace(opts, up=scene_up(Path(out)))
    series = Path(out) / SHELL_XDMF_NAME
    if not series.is_file() or not series.with_suffix(".h5").is_file():
        raise InputError(f"{series}: no shell series to render (run a scene with a [shell] "
                         "table first)")
    rest, faces, _, frames = read_shell_series(series)
    if not frames:
        raise InputError(f"{series}: the series has no step")
    rank, size = (0, 1) if comm is None else (comm.rank, comm.size)
    folder = Path(out) / opts.frames_dir
    folder.mkdir(parents=True, exist_ok=True)
    spheres = ball_spheres(Path(out) / BALLS_XDMF_NAME)
    clim = colour_range(frames, opts)
    camera = view_camera(polydata(rest, faces, frames[0]), opts, spheres(frames[0].time))
    pngs = [folder / f"shell_{k:04d}.png" for k in range(len(frames))]
    for k in range(rank, len(frames), size):
        render_frame(polydata(rest, faces, frames[k]), pngs[k], clim, opts, camera,
                     spheres(frames[k].time))
    if comm is not None:
        comm.Barrier()
    if rank:
        return []
    last, gif = Path(out) / "shell.png", Path(out) / "shell.gif"
    shutil.copyfile(pngs[-1], last)  # the last frame's picture, not rendered twice
    write_gif(pngs, gif, opts)
    return [*pngs, last, gif]


def add_parser(commands: Any) -> Any:
    """Add the ``render`` sub-command to an argparse sub-parser collection; return it."""
    parser = commands.add_parser("render", help="render the shell of a run: PNG frames, "
                                 "shell.png and shell.gif (off-screen, pyvista)")
    parser.add_argument("out", type=Path, help="output directory of a run (holds shell.xdmf)")
    parser.add_argument("--width", type=int, default=RenderOptions.width, help="image width")
    parser.add_argument("--height", type=int, default=RenderOptions.height,
                        help="image height")
    return parser


def command_render(args: argparse.Namespace) -> int:
    """Run the ``render`` sub-command; return the exit code.

    Under ``mpiexec -n N`` the ranks share the frames (:func:`render_run`); rank 0 reports.
    """
    from models.backend import MPI

    comm = MPI.COMM_WORLD
    written = render_run(args.out, RenderOptions(width=args.width, height=args.height),
                         comm if comm.size > 1 else None)
    if comm.rank == 0:
        print(f"rendered {len(written)} files into {args.out} (shell.png, shell.gif, "
              f"{len(written) - 2} frames)", flush=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry point: ``python -m wrinkles.render OUT_DIR``."""
    parser = argparse.ArgumentParser(prog="wrinkles")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["render", *(sys.argv[1:] if argv is None else argv)])
    try:
        return command_render(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return exc.exit_code


if __name__ == "__main__":
    raise SystemExit(main())
