"""The wrinkle demo scene end to end from the CLI (short and coarse), its files, the render
command, the ``[shell]`` table's validation, and 1 vs 2 ranks."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy.spatial import cKDTree
from support import (
    DEFAULT_SCENE,
    REPO,
    progress_lines,
    read_series,
    read_shell_series,
    wrinkles,
)

from meshes.errors import InputError
from wrinkles.scene import load_scene

DEFAULT = DEFAULT_SCENE
COARSE = ["--frames", "2", "--set", "shell.subdivision.levels=1", "--set", "output.render=false",
          "--set", "body.dt=0.4"]
"""2 frames of 4 % compression each, one subdivision level, no render at the end."""


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    proc = wrinkles("run", str(DEFAULT), "--out", str(out), *COARSE)
    assert proc.returncode == 0, proc.stderr
    return out


def test_demo_writes_consistent_body_and_shell_series(demo):
    body_pts, tets, body_steps = read_shell_series(demo / "body.xdmf")
    pts, tris, steps = read_shell_series(demo / "shell.xdmf")
    assert tets.shape[1] == 4 and tris.shape[1] == 3
    assert [t for t, _ in steps] == pytest.approx([0.0, 0.4, 0.8])
    assert [t for t, _ in body_steps] == pytest.approx([0.0, 0.4, 0.8])
    for _, data in steps:
        assert data["displacement"].shape == pts.shape
        assert data["bending_energy_density"].shape == (pts.shape[0],)
        assert data["cluster_id"].shape == (pts.shape[0],)
        assert all(np.all(np.isfinite(v)) for v in data.values())
    for _, data in body_steps:
        assert data["displacement"].shape == body_pts.shape
    # the moving end is pinned at -0.02 m/unit * 0.8 = -16 mm in x; the shell moved with the
    # body up to its wrinkles/sliding in the null space of H (measured -17.1 mm)
    assert body_steps[-1][1]["displacement"][:, 0].min() == pytest.approx(-0.016, abs=1e-12)
    assert steps[-1][1]["displacement"][:, 0].min() == pytest.approx(-0.016, rel=0.1)
    summary = json.loads((demo / "summary.json").read_text())
    frames = summary["frames"]
    assert len(frames) == 2 and summary["run"]["status"] == "completed"
    assert summary["run"]["shell"]["vertices"] == pts.shape[0]
    assert set(frames[0]["stage_times"]) == {"body", "shell"}
    amplitude = [f["details"]["wrinkle_amplitude_rel"] for f in frames]
    print("wrinkle amplitude / edge", amplitude)
    assert all(f["details"]["shell_converged"] for f in frames)
    assert amplitude[-1] > 0.1


def test_render_writes_png_and_gif(demo):
    proc = wrinkles("render", str(demo), "--width", "320", "--height", "240")
    assert proc.returncode == 0, proc.stderr
    from PIL import Image

    png, gif = demo / "shell.png", demo / "shell.gif"
    with Image.open(png) as image:
        assert image.size == (320, 240)
        pixels = np.asarray(image.convert("RGB"), dtype=float)
    assert pixels.std() > 10.0  # not a blank image
    frames = sorted((demo / "frames").glob("shell_*.png"))
    assert len(frames) == 3
    with Image.open(gif) as anim:
        assert anim.n_frames == 3
        for k, path in enumerate(frames):  # each GIF frame is its PNG in 256 colours
            anim.seek(k)
            with Image.open(path) as frame:
                error = np.abs(np.asarray(anim.convert("RGB"), dtype=float)
                               - np.asarray(frame.convert("RGB"), dtype=float)).mean()
            print(f"GIF frame {k}: mean |RGB - PNG| {error:.2f} of 255")
            assert error < 4.0  # measured 1.5 on the demo's frames


def test_render_without_series_is_an_input_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "wrinkles.render", str(tmp_path)],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 1
    assert "no shell series to render" in proc.stderr


@pytest.mark.parametrize(("override", "message"), [
    ("shell.skin.thicknes=1e-3", "unknown key 'shell.skin.thicknes'"),
    ("shell.coupling.mode='both'", "shell.coupling.mode"),
    ("shell.imperfection=-1.0", "shell.imperfection"),
])
def test_shell_table_is_validated(override, message):
    with pytest.raises(InputError, match=message.replace(".", r"\.")):
        load_scene(DEFAULT, [override])


@pytest.mark.mpi
def test_two_ranks_give_the_serial_shell(demo, mpiexec, tmp_path):
    """The shell is solved on rank 0 from B u gathered over the ranks: 2 ranks reproduce the
    serial run to the body/shell solver tolerances."""
    proc = mpiexec(["-m", "wrinkles", "run", str(DEFAULT), "--out", str(tmp_path), *COARSE],
                   timeout=600)
    assert proc.returncode == 0, proc.stderr
    _, _, serial = read_shell_series(demo / "shell.xdmf")
    _, _, parallel = read_shell_series(tmp_path / "shell.xdmf")
    diff = np.abs(serial[-1][1]["displacement"] - parallel[-1][1]["displacement"]).max()
    print("max shell displacement difference 1 vs 2 ranks", diff)
    assert diff < 1e-6


def test_resume_with_a_shell_continues_the_run(demo, tmp_path):
    """The checkpoint holds the shell state: --resume of the 2-frame demo with --frames 3
    continues at frame 3 and appends one step to both series (a copy of the demo output)."""
    out = tmp_path / "demo"
    shutil.copytree(demo, out)
    extended = ["--frames", "3", *COARSE[2:]]
    proc = wrinkles("run", str(DEFAULT), "--out", str(out), "--resume", *extended)
    assert proc.returncode == 0, proc.stderr
    assert progress_lines(proc.stdout)[0].split()[1] == "3/3"
    for name in ("body.xdmf", "shell.xdmf"):
        _, _, steps = read_shell_series(out / name)
        assert [t for t, _ in steps] == pytest.approx([0.0, 0.4, 0.8, 1.2])
    frames = json.loads((out / "summary.json").read_text())["frames"]
    assert [f["frame"] for f in frames] == [1, 2, 3]
    assert frames[-1]["details"]["shell_converged"]


def test_multigrid_linear_method_runs_a_scene_to_the_direct_minimiser(tmp_path):
    """``shell.newton.linear_method = "multigrid"`` (PCMG on the scene's own subdivision
    hierarchy, Gauss-Newton Hessian) solved to 1e-8 (fixed forcing) converges each frame to the
    minimiser the direct solve finds with the same Hessian mode, to the solver tolerance (the
    scene default, inexact Newton down to 1e-4, may take another path to another wrinkled
    minimiser: tests/test_wrinkles/test_fast_defaults.py)."""
    gn = ["--set", "shell.solver.options.energy.hessian_mode=gauss_newton",
          "--set", "shell.imperfection=0.0",
          "--set", "shell.solver.options.newton.multigrid.forcing=fixed",
          "--set", "shell.solver.options.newton.multigrid.rtol=1e-8"]
    energies = {}
    for method in ("direct", "multigrid"):
        out = tmp_path / method
        proc = wrinkles("run", str(DEFAULT), "--out", str(out), *COARSE, *gn,
                        "--set", f"shell.solver.method={method}")
        assert proc.returncode == 0, proc.stderr[-2000:]
        frames = json.loads((out / "summary.json").read_text())["frames"]
        assert all(f["details"]["shell_converged"] for f in frames)
        energies[method] = np.array([f["details"]["shell_energy"] for f in frames])
    print("shell energies direct", energies["direct"], "multigrid", energies["multigrid"])
    np.testing.assert_allclose(energies["multigrid"], energies["direct"], rtol=1e-6)


@pytest.fixture(scope="module")
def multigrid_serial(tmp_path_factory) -> Path:
    """One serial frame of the multigrid-sized default scene (the split tests' reference)."""
    out = tmp_path_factory.mktemp("np1")
    serial = wrinkles(*SPLIT_ARGS, "--out", str(out))
    assert serial.returncode == 0, serial.stderr[-2000:]
    return out


SPLIT_ARGS = ["run", str(DEFAULT), "--frames", "1", "--set", "output.render=false",
              "--set", "body.dt=0.1", "--set", "shell.imperfection=0.0",
              "--set", "shell.solver.rtol=1e-5",
              "--set", "shell.solver.options.energy.hessian_mode=gauss_newton",
              "--set", "shell.solver.options.newton.multigrid.forcing=fixed",
              "--set", "shell.solver.options.newton.multigrid.rtol=1e-8",
              "--set", "shell.solver.options.newton.multigrid.phase_space=true"]
"""One frame of the default scene on one path to one minimiser (see the test below); the phase
space asked for (the code leaves it out below 8 000 vertices), so that its split form is run."""


@pytest.mark.mpi
@pytest.mark.parametrize("ranks", [2, 3])
def test_ranks_split_the_multigrid_shell_and_keep_its_frames(multigrid_serial, ranks, mpiexec,
                                                             tmp_path):
    """``mpiexec -n 2`` (and ``-n 3``, more ranks than cores here) ``wrinkles run`` on a
    multigrid-sized shell (2 610 vertices, two levels) splits the shell over the ranks
    (distributed Hessian rows, PCMG and phase space over PETSc) and takes the serial run's
    steps: the same Newton iterations per frame within one and the same shell to the solver
    tolerance (Gauss-Newton Hessian, CG to 1e-8, no imperfection: one path to one minimiser;
    with the exact Hessian the buckling frame's CG failures follow round-off and the runs may
    take other paths to other wrinkles)."""
    out = tmp_path / f"np{ranks}"
    proc = mpiexec(["-m", "wrinkles", *SPLIT_ARGS, "--out", str(out)], n=ranks, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"split over {ranks} ranks" in proc.stdout
    runs = [json.loads((d / "summary.json").read_text()) for d in (multigrid_serial, out)]
    assert runs[1]["run"]["shell"]["solver"]["method"] == "multigrid"
    for f1, f2 in zip(runs[0]["frames"], runs[1]["frames"], strict=True):
        d1, d2 = f1["details"], f2["details"]
        assert d1["shell_converged"] and d2["shell_converged"]
        assert abs(d1["shell_iterations"] - d2["shell_iterations"]) <= 1
        assert d2["shell_energy"] == pytest.approx(d1["shell_energy"], rel=1e-8)
    _, _, one = read_shell_series(multigrid_serial / "shell.xdmf")
    _, _, split = read_shell_series(out / "shell.xdmf")
    diff = np.abs(one[-1][1]["displacement"] - split[-1][1]["displacement"]).max()
    print("iterations", [f["details"]["shell_iterations"] for r in runs for f in r["frames"]],
          f"max shell displacement difference 1 vs {ranks} ranks", diff)
    assert diff < 1e-7


@pytest.mark.mpi
def test_a_two_rank_run_resumed_on_one_rank_continues_the_serial_frames(mpiexec, tmp_path):
    """The checkpoint's shell state does not depend on the rank count: 2 frames on 2 ranks
    (the split shell), then ``--resume --frames 3`` on one rank, ends where 3 serial frames
    end, to the solver tolerance; the body's XDMF series holds all 4 steps (frame 3 in the
    2-rank file's node order) and the shell's too."""
    out = tmp_path / "np2"
    proc = mpiexec(["-m", "wrinkles", "run", str(DEFAULT), "--out", str(out), *COARSE],
                   timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    extended = ["--frames", "3", *COARSE[2:]]
    resumed = wrinkles("run", str(DEFAULT), "--out", str(out), "--resume", *extended)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    straight = wrinkles("run", str(DEFAULT), "--out", str(tmp_path / "np1"), *extended)
    assert straight.returncode == 0, straight.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert [f["frame"] for f in summary["frames"]] == [1, 2, 3]
    assert [r["ranks"] for r in summary["run"]["restarts"]] == [1]
    positions = []
    for run in (out, tmp_path / "np1"):
        with h5py.File(run / "checkpoint.h5", "r") as h5:
            assert h5.attrs["frame"] == 3
            positions.append(h5["stages/shell/positions"][...])
    diff = np.abs(positions[0] - positions[1]).max()
    print("max shell position difference, resumed on 1 rank vs serial", diff)
    assert diff < 1e-6
    (p_resumed, s_resumed), (p_serial, s_serial) = (read_series(run / "body.xdmf")
                                                    for run in (out, tmp_path / "np1"))
    assert len(s_resumed) == len(s_serial) == 4
    _, index = cKDTree(p_resumed).query(p_serial)
    last = [s[-1][1]["displacement"] for s in (s_resumed, s_serial)]
    body_diff = np.abs(last[0][index] - last[1]).max()
    print("max body displacement difference of the last step", body_diff)
    assert body_diff < 1e-6
    assert len(read_shell_series(out / "shell.xdmf")[2]) == 4
