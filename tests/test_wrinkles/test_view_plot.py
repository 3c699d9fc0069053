"""What a user opens after a run: ``wrinkles view`` (ParaView script, .pvd), ``wrinkles plot``,
the balls' series, and the render with the ball in it."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import REPO, SCENE, folded_plate, wrinkles

from wrinkles.rigid_output import read_balls
from wrinkles.view import HEADLESS

BALL_SOFA = ("--frames", "4", "--set", "shell.subdivision.levels=0", "--set", "output.render=true")


@pytest.fixture(scope="module")
def sofa(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sofa") / "out"
    proc = wrinkles("run", str(SCENE), "--out", str(out), *BALL_SOFA, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return out


def test_balls_series_holds_every_frame_with_the_summary_state(sofa):
    radii, steps = read_balls(sofa / "balls.xdmf")
    frames = json.loads((sofa / "summary.json").read_text())["frames"]
    assert radii.tolist() == [0.15]
    assert [s.time for s in steps] == pytest.approx([0.0] + [f["time"] for f in frames])
    np.testing.assert_allclose(steps[0].centers[0], [1.0, 0.35, 0.63])
    for step, frame in zip(steps[1:], frames, strict=True):
        np.testing.assert_allclose(step.centers[0], frame["details"]["balls"][0]["center"])
        np.testing.assert_allclose(step.velocities[0], frame["details"]["balls"][0]["velocity"])
    assert steps[-1].centers[0, 2] < steps[0].centers[0, 2]  # it fell


def test_balls_series_opens_in_the_legacy_xdmf_reader(sofa):
    script = ("import sys, vtk; r = vtk.vtkXdmfReader(); r.SetFileName(sys.argv[1]); r.Update();"
              "d = r.GetOutputDataObject(0); d = d.GetBlock(0) if d.IsA('vtkMultiBlockDataSet') "
              "else d; print(d.GetNumberOfPoints(), d.GetPointData().GetArray('radius')"
              ".GetValue(0))")
    proc = subprocess.run([sys.executable, "-c", script, str(sofa / "balls.xdmf")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    points, radius = proc.stdout.split()
    assert int(points) == 1 and float(radius) == pytest.approx(0.15)


def test_render_draws_the_ball(sofa, tmp_path):
    """The last frame with the ball, against the same render without the ball series: the
    ball's pixels (a sphere in the ball colour) are there only with it."""
    from PIL import Image

    with_ball = np.asarray(Image.open(sofa / "shell.png").convert("RGB"), dtype=float)
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("shell.xdmf", "shell.h5", "shell.steps"):
        source = sofa / name
        (shutil.copytree if source.is_dir() else shutil.copy)(source, bare / name)
    proc = wrinkles("render", str(bare))
    assert proc.returncode == 0, proc.stderr
    without = np.asarray(Image.open(bare / "shell.png").convert("RGB"), dtype=float)
    changed = np.abs(with_ball - without).sum(axis=2) > 30.0
    assert changed.mean() > 0.01  # the sphere covers part of the picture


def test_plot_writes_a_png_with_four_panels(sofa):
    proc = wrinkles("plot", str(sofa))
    assert proc.returncode == 0, proc.stderr
    from PIL import Image

    image = Image.open(sofa / "plots.png")
    assert image.size[0] > 800 and image.size[1] > 600


def test_plot_marks_the_frames_whose_shell_stopped_above_its_tolerance(sofa):
    """The iteration panel gets red crosses on the shell's curve at the frames whose
    ``shell_converged`` is false, and none for a run whose frames all converged."""
    import copy

    import matplotlib.pyplot as plt

    from wrinkles.plot import read_summary, summary_figure, unconverged_frames

    summary = read_summary(sofa)
    assert unconverged_frames(summary["frames"]) == []
    labels = [line.get_label() for line in summary_figure(summary, "sofa").axes[1].lines]
    assert "shell NOT converged" not in labels
    stopped = copy.deepcopy(summary)
    stopped["frames"][1]["details"]["shell_converged"] = False
    assert unconverged_frames(stopped["frames"]) == [stopped["frames"][1]["frame"]]
    fig = summary_figure(stopped, "sofa")
    (cross,) = [line for line in fig.axes[1].lines if line.get_label() == "shell NOT converged"]
    assert list(cross.get_xdata()) == [stopped["frames"][1]["frame"]]
    assert list(cross.get_ydata()) == [stopped["frames"][1]["details"]["shell_iterations"]]
    assert fig.texts[0].get_text().endswith("; shell NOT converged in 1)")
    plt.close("all")


def test_plot_marks_the_frames_whose_shell_passes_through_itself(sofa):
    """Magenta rings on the shell's iteration curve at the frames with
    ``shell_self_intersections > 0`` (the sofa's own frames have none), counted in the
    title."""
    import copy

    import matplotlib.pyplot as plt

    from wrinkles.plot import read_summary, self_intersecting_frames, summary_figure

    summary = read_summary(sofa)
    assert self_intersecting_frames(summary["frames"]) == []
    assert all(r["details"]["shell_self_intersections"] == 0 for r in summary["frames"])
    crossed = copy.deepcopy(summary)
    for r in crossed["frames"][-2:]:
        r["details"]["shell_self_intersections"] = 3
    marked = [r["frame"] for r in crossed["frames"][-2:]]
    assert self_intersecting_frames(crossed["frames"]) == marked
    fig = summary_figure(crossed, "sofa")
    (ring,) = [line for line in fig.axes[1].lines
               if line.get_label() == "shell self-intersecting"]
    assert list(ring.get_xdata()) == marked
    assert fig.texts[0].get_text().endswith("; shell self-intersecting in 2)")
    plt.close("all")


def test_plot_of_a_directory_without_a_run_is_bad_input(tmp_path):
    proc = wrinkles("plot", str(tmp_path))
    assert proc.returncode == 1
    assert "summary.json: no summary" in proc.stderr and "Traceback" not in proc.stderr


def test_view_writes_a_paraview_script_and_pvd_files_pyvista_reads(sofa):
    proc = wrinkles("view", str(sofa), "--pvd")
    assert proc.returncode == 0, proc.stderr
    script = (sofa / "view.py").read_text()
    compile(script, "view.py", "exec")
    assert "bending_energy_density" in script and "UseLogScale = 1" in script
    assert "WarpByVector" in script and "Glyph" in script
    check = ("import json, sys, pyvista as pv\n"
             "out = {}\n"
             "for name in sys.argv[1:]:\n"
             "    r = pv.get_reader(name)\n"
             "    r.set_active_time_point(len(r.time_values) - 1)\n"
             "    m = r.read()[0]\n"
             "    out[name.rsplit('/', 1)[-1]] = [len(r.time_values), m.n_points,"
             " sorted(m.point_data.keys())]\n"
             "print(json.dumps(out))\n")
    pvds = [str(sofa / "vtk" / f"{n}.pvd") for n in ("body", "shell", "balls")]
    proc = subprocess.run([sys.executable, "-c", check, *pvds], capture_output=True, text=True,
                          timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["body.pvd"][0] == got["shell.pvd"][0] == got["balls.pvd"][0] == 5
    assert "bending_energy_density" in got["shell.pvd"][2]
    assert got["balls.pvd"][1:] == [1, ["radius", "velocity"]]


@pytest.mark.skipif(shutil.which("pvpython") is None or shutil.which("xvfb-run") is None,
                    reason="ParaView (apt-get install paraview xvfb) not installed")
def test_view_script_runs_in_pvpython(sofa):
    """ParaView 5.11 (Debian) runs the script and writes view.png (under a virtual display)."""
    proc = wrinkles("view", str(sofa))
    assert proc.returncode == 0, proc.stderr
    run = subprocess.run([*HEADLESS, str(sofa / "view.py")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (sofa / "view.png").stat().st_size > 10_000


def plate_through_itself() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The plate folded to 3.5 rad (:func:`support.folded_plate`) and its vertices'
    ``self_intersecting`` flags: ``(rest, faces, x, flags)``."""
    from models.shell.self_intersection import intersecting_faces, vertex_flags

    rest, faces, x = folded_plate(3.5)
    return rest, faces, x, vertex_flags(faces, intersecting_faces(x, faces), len(x))


@pytest.mark.skipif(shutil.which("pvpython") is None or shutil.which("xvfb-run") is None,
                    reason="ParaView (apt-get install paraview xvfb) not installed")
def test_view_script_marks_self_intersecting_faces_in_pvpython(tmp_path):
    """A shell series whose last step has faces flagged ``self_intersecting`` (a plate folded
    through itself): the view script shows them in magenta and says so; ParaView writes the
    picture."""
    import numpy as np

    from wrinkles.shell_output import ShellFrame, ShellSeries

    rest, faces, x, crossing = plate_through_itself()
    assert crossing.sum() > 10
    series = ShellSeries(tmp_path / "shell.xdmf", rest, faces, np.zeros(len(x), dtype=np.int64))
    series.write(ShellFrame(0.0, np.zeros_like(x), np.full(len(x), 1e-3), np.zeros(len(x))))
    series.write(ShellFrame(1.0, x - rest, np.full(len(x), 1e-3), crossing))
    proc = wrinkles("view", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    run = subprocess.run([*HEADLESS, str(tmp_path / "view.py")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "self-intersecting faces at the last step" in run.stdout
    assert (tmp_path / "view.png").stat().st_size > 10_000


def test_renders_draw_self_intersecting_faces_in_magenta(tmp_path):
    """A plate folded through itself rendered off-screen: with its ``self_intersecting``
    vertices the picture has magenta pixels (the crossing faces), without them none (magenta
    is in neither the colour map nor the background)."""
    import numpy as np
    from PIL import Image

    from wrinkles.render import RenderOptions, polydata, render_frame
    from wrinkles.shell_output import ShellFrame

    rest, faces, x, crossing = plate_through_itself()
    density = 1e-3 * (1.0 + x[:, 0])
    opts = RenderOptions(width=400, height=300, view=(0.3, -1.0, 0.6))
    counts = []
    for flags in (crossing, np.zeros(len(x))):
        path = tmp_path / f"plate_{int(flags.sum())}.png"
        render_frame(polydata(rest, faces, ShellFrame(1.0, x - rest, density, flags)), path,
                     (-3.0, -2.0), opts)
        rgb = np.asarray(Image.open(path).convert("RGB"), dtype=int)
        magenta = (rgb[..., 0] > 200) & (rgb[..., 1] < 80) & (rgb[..., 2] > 200)
        counts.append(int(magenta.sum()))
    print("magenta pixels with / without the flags", counts)
    assert counts[0] > 100 and counts[1] == 0
