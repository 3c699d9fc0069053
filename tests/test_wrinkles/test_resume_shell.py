"""A run with an embedded shell survives SIGKILL: ``--resume`` reproduces the straight run.

The demo scene (compressed bar, 1000x skin, one-way coupling), coarse: one subdivision level,
6 frames of 3 % compression. The run is killed at random moments after >= 2 completed frames
(in the shell Newton solve, the shell or body series transaction, or the checkpoint write),
then resumed. The checkpoint carries the shell state (positions, previous target, tolerance
reference, coupling force, the Newton's shift memory), the body and shell series drop the
steps written after it, so the resumed run takes the same iterates as the straight run:
shell displacements, body and shell energies agree to solver tolerance (they are in fact
bitwise equal).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import numpy as np
import pytest
from killrun import kill_after_frames
from support import DEFAULT_SCENE as DEFAULT
from support import read_shell_series as read_series
from support import wrinkles

from wrinkles.output import complete_steps
from wrinkles.shell_output import read_shell_series

FRAMES = 6
ARGS = ["--frames", str(FRAMES), "--set", "shell.subdivision.levels=1", "--set",
        "output.render=false", "--set", "body.dt=0.15"]
"""6 frames of 3 % compression each (the pin moves by -3 mm per frame)."""
RTOL = 1e-9
"""Agreement asked of the resumed run (shell Newton rtol is 1e-6, body 1e-9)."""


def args(out: Path, *extra: str) -> list[str]:
    return ["run", str(DEFAULT), "--out", str(out), *ARGS, *extra]


def start_and_kill(out: Path, after: int, delay: float, *extra: str) -> int:
    """Start the run, SIGKILL it ``delay`` s after ``after`` frames are done; frames done."""
    return kill_after_frames(args(out, *extra), out, after, delay)


def assert_shell_series_intact(out: Path, at_least: int) -> int:
    """``shell.xdmf`` parses, every listed step is readable; return the step count."""
    path = out / "shell.xdmf"
    listed = len(list(ET.parse(path).getroot().iter("Time")))
    assert len(complete_steps(path)) == listed >= at_least + 1  # + the rest state
    with h5py.File(out / "shell.h5", "r") as h5:
        assert h5["Mesh/geometry"].shape[1] == 3
    return listed


def summary_frames(out: Path) -> list[dict]:
    return json.loads((out / "summary.json").read_text())["frames"]


@pytest.fixture(scope="module")
def straight(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("straight") / "out"
    proc = wrinkles(*args(out))
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.mark.parametrize("delays", [(0.0, 0.15), (0.3, 0.05)])
def test_killed_shell_run_resumed_matches_straight_run(straight, tmp_path, delays):
    out = tmp_path / "out"
    done = start_and_kill(out, 2, delays[0])
    assert done >= 2
    seen = [assert_shell_series_intact(out, done)]
    done = start_and_kill(out, done + 1, delays[1], "--resume")
    seen.append(assert_shell_series_intact(out, done))
    proc = wrinkles(*args(out, "--resume"))
    assert proc.returncode == 0, proc.stderr
    _, _, _, ref = read_shell_series(straight / "shell.xdmf")
    _, _, _, got = read_shell_series(out / "shell.xdmf")
    assert [f.time for f in got] == pytest.approx([f.time for f in ref], abs=1e-14)
    assert len(got) == FRAMES + 1
    scale = max(np.abs(f.displacement).max() for f in ref)
    err = max(np.abs(g.displacement - r.displacement).max() for g, r in zip(got, ref,
                                                                           strict=True))
    r_frames, g_frames = summary_frames(straight), summary_frames(out)
    energy = [np.array([[f["energy"], f["details"]["shell_energy"]] for f in frames])
              for frames in (r_frames, g_frames)]
    e_err = float(np.abs(energy[1] - energy[0]).max() / np.abs(energy[0]).max())
    print(f"steps on disk after the kills {seen}, frames done {done}; shell displacement "
          f"|diff| {err:.3e} m of {scale:.3e} m; energy rel diff {e_err:.3e}; shell iterations "
          f"straight {[f['details']['shell_iterations'] for f in r_frames]} resumed "
          f"{[f['details']['shell_iterations'] for f in g_frames]}")
    assert err <= RTOL * scale
    assert e_err <= RTOL
    assert len(json.loads((out / "summary.json").read_text())["run"]["restarts"]) == 2
    _, _, body_steps = read_series(out / "body.xdmf")  # the body series was resumed too
    assert len(body_steps) == FRAMES + 1


def test_resume_may_change_the_solver_threads(straight, tmp_path):
    """Threads are not physics: a run resumed with ``shell.energy.threads = 2`` (round-off
    differences only) continues instead of being refused as another scene."""
    out = tmp_path / "out"
    first = wrinkles("run", str(DEFAULT), "--out", str(out), *ARGS[2:], "--frames", "3")
    assert first.returncode == 0, first.stderr
    proc = wrinkles(*args(out, "--resume", "--set", "shell.solver.threads=2"))
    assert proc.returncode == 0, proc.stderr
    r_frames, g_frames = summary_frames(straight), summary_frames(out)
    assert len(g_frames) == FRAMES
    energy = [np.array([f["details"]["shell_energy"] for f in frames])
              for frames in (r_frames, g_frames)]
    print(f"shell energies straight {energy[0]}, resumed on two threads {energy[1]}")
    np.testing.assert_allclose(energy[1], energy[0], rtol=1e-6)


def test_a_series_written_before_the_self_intersection_field_resumes_with_it(tmp_path):
    """A series whose steps carry no ``self_intersecting`` (written before it existed) is
    continued: its steps keep their two fields in the XML, the new step has three, and both
    readers (ours and meshio's) read every step, ours giving None for the old ones."""
    from meshes.shells import grid_plate
    from wrinkles.shell_output import ShellFrame, ShellSeries

    rest, faces = grid_plate(3, 3)
    n = rest.shape[0]
    path = tmp_path / "shell.xdmf"
    old = ShellSeries(path, rest, faces, np.zeros(n, dtype=np.int64))
    for t in (0.0, 1.0):
        old.write(ShellFrame(t, np.full((n, 3), t), np.full(n, t)))
    resumed = ShellSeries(path, rest, faces, np.zeros(n, dtype=np.int64), resume_after=1.0)
    crossing = np.arange(n) % 2.0
    resumed.write(ShellFrame(2.0, np.full((n, 3), 2.0), np.full(n, 2.0), crossing))
    grids = [g for g in ET.parse(path).getroot().iter("Grid") if g.find("Time") is not None]
    names = [[a.get("Name") for a in g.iter("Attribute")] for g in grids]
    assert [len(x) for x in names] == [3, 3, 4]  # cluster_id on every step
    assert "self_intersecting" in names[2] and "self_intersecting" not in names[0]
    _, _, _, frames = read_shell_series(path)
    assert [f.self_intersecting is None for f in frames] == [True, True, False]
    assert np.array_equal(frames[2].self_intersecting, crossing)
    _, _, steps = read_series(path)
    assert [t for t, _ in steps] == [0.0, 1.0, 2.0]
    assert np.array_equal(steps[2][1]["self_intersecting"], crossing)


def test_a_checkpoint_of_another_surface_is_refused_and_the_run_kept(tmp_path):
    """A checkpoint whose shell arrays sit on other vertices (as a run written from another
    surface with as many vertices would: here its target and positions reversed) is refused
    with exit 1 naming the checkpoint, and the run on disk is left as it was."""
    out = tmp_path / "out"
    first = wrinkles("run", str(DEFAULT), "--out", str(out), *ARGS[2:], "--frames", "2")
    assert first.returncode == 0, first.stderr
    with h5py.File(out / "checkpoint.h5", "r+") as h5:
        for name in ("target", "positions"):
            data = h5[f"stages/shell/{name}"]
            data[...] = data[...][::-1]
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    proc = wrinkles(*args(out, "--resume"))
    assert proc.returncode == 1, proc.stderr
    assert "checkpoint: the shell's stored target" in proc.stderr
    assert "another surface" in proc.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
