"""The ``wrinkles`` command line end to end: output files, exit codes, serial vs 2 ranks."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest
from scipy.spatial import cKDTree
from support import DROP_BLOCK, REPO, progress_lines, read_series, wrinkles

DEFAULT = DROP_BLOCK
G = 9.81


@pytest.fixture(scope="module")
def five_frames(tmp_path_factory) -> tuple[subprocess.CompletedProcess[str], Path]:
    out = tmp_path_factory.mktemp("run") / "out"
    return wrinkles("run", str(DEFAULT), "--frames", "5", "--out", str(out)), out


def output_of(run: tuple[subprocess.CompletedProcess[str], Path]) -> Path:
    """The output directory of a run that must have succeeded."""
    proc, out = run
    assert proc.returncode == 0, proc.stderr
    return out


def test_run_exits_zero_with_one_progress_line_per_frame(five_frames):
    proc, _ = five_frames
    assert proc.returncode == 0, proc.stderr
    lines = progress_lines(proc.stdout)
    assert [line.split()[1] for line in lines] == [f"{k}/5" for k in range(1, 6)]
    for key in ("t=", "newton=", "energy=", "min detF=", "wall="):
        assert all(key in line for line in lines)


def test_xdmf_series_read_back_by_meshio(five_frames):
    out = output_of(five_frames)
    assert (out / "body.xdmf").is_file() and (out / "body.h5").is_file()
    points, steps = read_series(out / "body.xdmf")
    assert len(steps) == 6  # the initial state and 5 frames
    times = np.array([t for t, _ in steps])
    np.testing.assert_allclose(times, 0.01 * np.arange(6), rtol=0, atol=1e-12)
    for _, data in steps:
        assert set(data) == {"displacement", "velocity"}
        for values in data.values():
            assert values.shape == points.shape and np.all(np.isfinite(values))
    # before touching the ground (2 cm gap) the block falls freely: implicit Euler gives
    # v_n = -g n dt and u_n = -g dt^2 n (n + 1) / 2 exactly (the potential is quadratic)
    for n, (_, data) in enumerate(steps):
        np.testing.assert_allclose(data["velocity"][:, 2], -G * 0.01 * n, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(data["displacement"][:, 2], -G * 1e-4 * n * (n + 1) / 2,
                                   rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(data["displacement"][:, :2], 0.0, atol=1e-12)


def test_h5_agrees_with_meshio(five_frames):
    """The mesh lives in body.h5, each frame in its own body.steps/step_<k>.h5 (kill-safe)."""
    out = output_of(five_frames)
    points, steps = read_series(out / "body.xdmf")
    with h5py.File(out / "body.h5", "r") as h5:
        np.testing.assert_array_equal(h5["Mesh/mesh/geometry"][...], points)
    files = sorted((out / "body.steps").glob("step_*.h5"))
    assert len(files) == len(steps) == 6
    with h5py.File(files[-1], "r") as h5:
        for name in ("displacement", "velocity"):
            (key,) = h5["Function"][name]
            np.testing.assert_array_equal(h5["Function"][name][key][...], steps[-1][1][name])


def test_summary_has_one_record_per_frame(five_frames):
    out = output_of(five_frames)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["status"] == "completed" and summary["run"]["ranks"] == 1
    assert [r["frame"] for r in summary["frames"]] == [1, 2, 3, 4, 5]
    assert summary["scene"]["time"]["frames"] == 5  # --frames is part of the resolved scene
    assert summary["scene"]["material"]["E"] == 5.0e4
    assert {"dolfinx", "petsc", "numpy", "mpi4py"} <= set(summary["versions"])
    for record in summary["frames"]:
        assert record["newton_iterations"] >= 1 and record["wall_time"] > 0
        assert 0.9 < record["min_det_f"] <= 1.0 + 1e-12
        assert set(record["stage_times"]) == {"body"}
    # free fall: E_total = kinetic + gravity is conserved up to the implicit Euler loss
    # -m g^2 dt^2 n / 2 (per step the numerical dissipation is m |v_{n+1} - v_n|^2 / 2)
    mass = 1000.0 * 0.4 * 0.4 * 0.2
    energies = np.array([r["energy"] for r in summary["frames"]])
    n = np.arange(1, 6)
    np.testing.assert_allclose(energies, -mass * G**2 * 1e-4 * n / 2, rtol=1e-8)


def test_solver_failure_exits_2_and_keeps_completed_frames(tmp_path):
    out = tmp_path / "out"
    proc = wrinkles("run", str(DEFAULT), "--frames", "8", "--out", str(out),
                    "--set", "newton.options.max_it=1", "--set", "newton.options.max_halvings=0")
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: body step failed")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["status"] == "failed" and summary["run"]["failed_frame"] == 6
    assert len(summary["frames"]) == 5  # free fall converges in one Newton step, contact not
    _, steps = read_series(out / "body.xdmf")
    assert len(steps) == 6


# --- bad input: exit 1, one line, no traceback ----------------------------------------------


def write_bad_mesh(path: Path) -> None:
    """Two tets touching at one vertex: a vertex-non-manifold body."""
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1],
                       [-1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=float)
    tets = np.array([[0, 1, 2, 3], [0, 4, 6, 5]])
    meshio.write(str(path), meshio.Mesh(points, [("tetra", tets)]))


def bad_scene(tmp_path: Path, kind: str) -> list[str]:
    text = DEFAULT.read_text()
    if kind == "key":
        text = text.replace("nu = 0.35", "nu = 0.35\ndensty = 1.0")
    elif kind == "nu":
        text = text.replace("nu = 0.35", "nu = 0.5")
    elif kind == "E":
        text = text.replace("E = 5.0e4", "E = -5.0e4")
    elif kind == "mesh":
        write_bad_mesh(tmp_path / "bad.vtu")
        text = re.sub(r"^params = .*$", "", text.replace('builder = "box"', 'file = "bad.vtu"'),
                      flags=re.MULTILINE)
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return ["run", str(path), "--frames", "1", "--out", str(tmp_path / "out")]


BAD_INPUTS = {
    "key": r"^error: scene\.toml: unknown key 'material\.densty' \(did you mean 'density'\?\)$",
    "nu": r"^error: scene\.toml: material\.nu must be < 0\.5",
    "E": r"^error: scene\.toml: material\.E must be > 0, got -50000\.0$",
    "mesh": r"^error: .*bad\.vtu: boundary vertex 0 joins 2 separate surface fans",
}


@pytest.mark.parametrize("kind", sorted(BAD_INPUTS))
def test_bad_scene_exits_1_with_one_line(tmp_path, kind):
    proc = wrinkles(*bad_scene(tmp_path, kind))
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    assert proc.stdout == ""
    assert re.match(BAD_INPUTS[kind], proc.stderr.strip()), proc.stderr


@pytest.mark.parametrize(("args", "pattern"), [
    (["run", "no/such/scene.toml"], r"^error: no/such/scene\.toml: scene file not found$"),
    (["run"], r"^error: the following arguments are required: scene \(see 'wrinkles run"),
    (["frobnicate"], r"^error: argument command: invalid choice: 'frobnicate'"),
    (["run", str(DEFAULT), "--frames", "two"], r"^error: argument --frames: invalid int"),
    (["run", str(DEFAULT), "--frames", "0"], r"^error: --frames: time\.frames must be >= 1"),
    (["run", str(DEFAULT), "--set", "materal.E=1"],
     r"^error: drop_block\.toml: unknown key 'materal' \(did you mean 'material'\?\)$"),
    (["run", str(DEFAULT), "--set", "newton.options.petsc.pc_type=hypre"],
     r"^error: drop_block\.toml: newton\.options: newton\.options\.petsc \{'pc_type': "
     r"'hypre'\}: PETSc refused them: .*Unable to find requested PC type hypre$"),
    (["check", str(DEFAULT), "--set", "newton.options.petsc.ksp_rtoll=1e-12"],
     r"^error: drop_block\.toml: newton\.options: newton\.options\.petsc\.ksp_rtoll = "
     r"1e-12: not read by PETSc"),
])
def test_bad_usage_exits_1_with_one_line(args, pattern):
    proc = wrinkles(*args)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    assert re.match(pattern, proc.stderr), proc.stderr


# --- the same scene on 1 and 2 ranks -----------------------------------------------------------


@pytest.mark.mpi
def test_serial_and_two_ranks_agree(tmp_path, mpiexec):
    frames = "10"  # falls for 5 frames, hits the ground in frame 6, then squashes
    serial = wrinkles("run", str(DEFAULT), "--frames", frames, "--out", str(tmp_path / "np1"))
    assert serial.returncode == 0, serial.stderr
    proc = mpiexec(["-m", "wrinkles", "run", str(DEFAULT), "--frames", frames,
                    "--out", str(tmp_path / "np2")], n=2, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert len(progress_lines(proc.stdout)) == 10  # rank 0 prints, once per frame
    p1, s1 = read_series(tmp_path / "np1" / "body.xdmf")
    p2, s2 = read_series(tmp_path / "np2" / "body.xdmf")
    assert p1.shape == p2.shape and len(s1) == len(s2) == 11
    distance, index = cKDTree(p2).query(p1)
    assert distance.max() < 1e-12  # same nodes, distributed differently
    scale = {name: max(np.abs(d[name]).max() for _, d in s1)
             for name in ("displacement", "velocity")}
    assert scale["displacement"] > 0.02  # the block fell 2 cm and squashed
    worst = 0.0
    for (t1, d1), (t2, d2) in zip(s1, s2, strict=True):
        assert t1 == pytest.approx(t2, abs=1e-14)
        for name in scale:
            worst = max(worst, np.abs(d2[name][index] - d1[name]).max() / scale[name])
    assert worst < 1e-9, worst  # to solver tolerance (Newton rtol 1e-8); measured ~1e-15
    summary = json.loads((tmp_path / "np2" / "summary.json").read_text())
    assert summary["run"]["ranks"] == 2 and len(summary["frames"]) == 10
    e1 = [r["energy"] for r in json.loads((tmp_path / "np1" / "summary.json").read_text())
          ["frames"]]
    np.testing.assert_allclose([r["energy"] for r in summary["frames"]], e1, rtol=1e-9)


def test_p2_static_scene_writes_p1_nodal_values(tmp_path):
    """compress_block (P2, static, moving pin): XDMF holds the P2 field at the mesh nodes."""
    out = tmp_path / "out"
    proc = wrinkles("run", str(REPO / "scenes" / "compress_block.toml"), "--frames", "2",
                    "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    points, steps = read_series(out / "body.xdmf")
    assert [t for t, _ in steps] == [0.0, 1.0, 2.0]
    top, bottom = np.isclose(points[:, 2], 0.2), np.isclose(points[:, 2], 0.0)
    assert top.sum() >= 9 and bottom.sum() >= 9
    for k, (_, data) in enumerate(steps):
        u = data["displacement"]
        np.testing.assert_allclose(u[top], np.tile([0.0, 0.0, -0.002 * k], (top.sum(), 1)),
                                   atol=1e-14)
        np.testing.assert_allclose(u[bottom], 0.0, atol=1e-14)
        np.testing.assert_allclose(data["velocity"], 0.0, atol=0)  # statics
    # the free sides bulge outwards under compression (nu = 0.45)
    side = np.isclose(points[:, 0], 0.4) & ~top & ~bottom
    assert side.any() and np.all(steps[2][1]["displacement"][side, 0] > 0)


@pytest.mark.mpi
@pytest.mark.parametrize("kind", ["mesh", "nu"])
def test_bad_input_on_two_ranks_exits_1_once(tmp_path, mpiexec, kind):
    """A mesh error found by rank 0 alone is broadcast: both ranks stop, one message."""
    proc = mpiexec(["-m", "wrinkles", *bad_scene(tmp_path, kind)], n=2, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert re.match(BAD_INPUTS[kind], proc.stderr.strip()), proc.stderr
