"""No run loses its frames: SIGKILL a run at random moments, check the files, ``--resume``.

The run is a block dropped on the ground (implicit Euler, penalty contact; written here, so
that edits of ``scenes/`` do not change the test) with 10 sub-steps of
1 ms per 10 ms frame, so a frame takes ~0.2 s and a kill lands anywhere in a frame: in the
Newton solves, in the XDMF append (``.work/``), in the commit renames or in the summary and
checkpoint writes. After every kill the committed ``body.xdmf`` / ``body.h5`` must parse and
every step in the XML must be readable; the resumed run must then reproduce a straight run.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import numpy as np
import pytest
from killrun import kill_after_frames
from scipy.spatial import cKDTree
from test_cli_run import read_series, wrinkles

from wrinkles.output import complete_steps

REPO = Path(__file__).resolve().parents[1]
FRAMES = 12
SETTINGS = ["--set", "body.dt=0.001", "--set", "time.steps_per_frame=10"]
DROP_SCENE = """
title = "soft block dropped 2 cm onto rigid ground"
[mesh]
builder = "box"
params = { lx = 0.4, ly = 0.4, lz = 0.2, h = 0.05, origin = [0.0, 0.0, 0.02] }
[material]
model = "neo_hookean"
E = 5.0e4
nu = 0.35
density = 1000.0
[body]
degree = 1
dynamics = "implicit_euler"
dt = 0.01
gravity = [0.0, 0.0, -9.81]
[[body.contacts]]
obstacle = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
[newton]
rtol = 1e-9
atol = 1e-10
max_it = 50
[time]
frames = 30
"""


def drop_scene(directory: Path) -> Path:
    """Write the drop scene (~1400 P1 tets, contact from frame 6 on) into ``directory``."""
    path = directory / "drop.toml"
    path.write_text(DROP_SCENE)
    return path


def run_args(out: Path, *extra: str) -> list[str]:
    """``wrinkles`` arguments of the drop scene (written beside ``out``) run into ``out``."""
    scene = drop_scene(out.parent)
    return ["run", str(scene), "--frames", str(FRAMES), "--out", str(out), *SETTINGS, *extra]


def start_and_kill(out: Path, after: int, delay: float, *extra: str) -> int:
    """Start a run, SIGKILL it ``delay`` s after ``after`` frames are done; return frames done."""
    return kill_after_frames(run_args(out, *extra), out, after, delay, timeout=120)


def assert_series_intact(out: Path, at_least: int) -> int:
    """The committed series parses, all its steps are readable; return the step count."""
    path = out / "body.xdmf"
    ET.parse(path)
    with h5py.File(out / "body.h5", "r") as h5:
        assert h5["Mesh/mesh/geometry"].shape[1] == 3
    listed = [g for c in ET.parse(path).getroot().iter("Grid") for g in c.findall("Grid")]
    readable = complete_steps(path)
    assert len(readable) == len(listed) >= at_least + 1  # + the initial state
    _, steps = read_series(path)  # meshio reads every step
    assert len(steps) == len(listed)
    assert all(np.all(np.isfinite(d["displacement"])) for _, d in steps)
    return len(listed)


@pytest.fixture(scope="module")
def straight(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("straight") / "out"
    proc = wrinkles(*run_args(out))
    assert proc.returncode == 0, proc.stderr
    return out


def energies(out: Path) -> np.ndarray:
    return np.array([r["energy"] for r in json.loads((out / "summary.json").read_text())
                     ["frames"]])


def assert_same_as(reference: Path, out: Path, atol_rel: float) -> None:
    p1, s1 = read_series(reference / "body.xdmf")
    p2, s2 = read_series(out / "body.xdmf")
    assert len(s1) == len(s2) == FRAMES + 1
    _, index = cKDTree(p2).query(p1)
    for (t1, d1), (t2, d2) in zip(s1, s2, strict=True):
        assert t1 == pytest.approx(t2, abs=1e-14)
        for name in ("displacement", "velocity"):
            scale = max(np.abs(d[name]).max() for _, d in s1)
            err = np.abs(d2[name][index] - d1[name]).max()
            assert err <= atol_rel * scale, (name, t1, err, scale)
    np.testing.assert_allclose(energies(out), energies(reference), rtol=atol_rel)


@pytest.mark.parametrize("delays", [(0.0, 0.05, 0.13), (0.02, 0.09, 0.17)])
def test_killed_three_times_then_resumed_matches_straight_run(straight, tmp_path, delays):
    out = tmp_path / "out"
    done = start_and_kill(out, 2, delays[0])
    assert done >= 2
    seen = [assert_series_intact(out, done)]
    for delay in delays[1:]:
        done = start_and_kill(out, done + 1, delay, "--resume")
        seen.append(assert_series_intact(out, done))
    print(f"steps on disk after each kill: {seen}")
    proc = wrinkles(*run_args(out, "--resume"))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert [r["frame"] for r in summary["frames"]] == list(range(1, FRAMES + 1))
    assert len(summary["run"]["restarts"]) == 3
    assert_same_as(straight, out, atol_rel=1e-12)  # state restored exactly: same iterates


def test_restart_is_an_alias_of_resume(straight, tmp_path):
    out = tmp_path / "out"
    assert wrinkles(*run_args(out)[:3], "5", *run_args(out)[4:]).returncode == 0
    proc = wrinkles(*run_args(out, "--restart"))
    assert proc.returncode == 0, proc.stderr
    assert [line.split()[1] for line in proc.stdout.splitlines()][0] == f"6/{FRAMES}"
    assert_same_as(straight, out, atol_rel=1e-12)


def test_damaged_work_copy_never_reaches_the_committed_series(tmp_path):
    """A kill during the append damages only ``.work/``: the next run overwrites it."""
    out = tmp_path / "out"
    assert wrinkles(*run_args(out)[:3], "3", *run_args(out)[4:]).returncode == 0
    work = out / ".work"
    (work / "body.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 64)  # truncated HDF5
    (work / "body.xdmf").write_text("<Xdmf><Domain><Grid")  # half-written XML
    assert assert_series_intact(out, 3) == 4
    proc = wrinkles(*run_args(out, "--resume")[:3], "5", *run_args(out, "--resume")[4:])
    assert proc.returncode == 0, proc.stderr
    assert assert_series_intact(out, 5) == 6
