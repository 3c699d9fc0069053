"""``wrinkles run --restart``: continue a run from its last completed frame (checkpoint.h5)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy.spatial import cKDTree
from support import DROP_BLOCK as DEFAULT
from support import progress_lines, read_series, wrinkles

from wrinkles.output import node_order, reorder_fields


@pytest.fixture(scope="module")
def straight(tmp_path_factory) -> Path:
    """The reference: 10 frames in one go."""
    out = tmp_path_factory.mktemp("straight") / "out"
    proc = wrinkles("run", str(DEFAULT), "--frames", "10", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    return out


def run_ok(*args: str) -> str:
    proc = wrinkles("run", str(DEFAULT), *args)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def assert_same_run(reference: Path, other: Path, rtol: float) -> None:
    p1, s1 = read_series(reference / "body.xdmf")
    p2, s2 = read_series(other / "body.xdmf")
    assert len(s1) == len(s2) == 11
    _, index = cKDTree(p2).query(p1)
    for (t1, d1), (t2, d2) in zip(s1, s2, strict=True):
        assert t1 == pytest.approx(t2, abs=1e-14)
        for name in ("displacement", "velocity"):
            scale = max(np.abs(d[name]).max() for _, d in s1)
            np.testing.assert_allclose(d2[name][index], d1[name], rtol=0, atol=rtol * scale)
    np.testing.assert_allclose(energies(other), energies(reference), rtol=rtol)


def test_restart_continues_bitwise(straight, tmp_path):
    out = tmp_path / "out"
    run_ok("--frames", "6", "--out", str(out))
    stdout = run_ok("--frames", "10", "--out", str(out), "--restart")
    assert [line.split()[1] for line in progress_lines(stdout)] == ["7/10", "8/10", "9/10", "10/10"]
    assert_same_run(straight, out, rtol=0.0)  # the state is restored exactly
    summary = json.loads((out / "summary.json").read_text())
    assert [r["frame"] for r in summary["frames"]] == list(range(1, 11))
    assert summary["run"]["restarts"] == [{"frame": 6, "time": pytest.approx(0.06),
                                           "ranks": 1}]


def test_restart_drops_output_written_after_the_checkpoint(straight, tmp_path):
    """A run killed after frame 4's checkpoint but after writing frames 5, 6 of output."""
    early, out = tmp_path / "early", tmp_path / "out"
    run_ok("--frames", "4", "--out", str(early))
    run_ok("--frames", "6", "--out", str(out))
    shutil.copy(early / "checkpoint.h5", out / "checkpoint.h5")
    stdout = run_ok("--frames", "10", "--out", str(out), "--restart")
    assert progress_lines(stdout)[0].split()[1] == "5/10"
    assert_same_run(straight, out, rtol=0.0)


def energies(out: Path) -> list[float]:
    return [r["energy"] for r in json.loads((out / "summary.json").read_text())["frames"]]


@pytest.mark.mpi
def test_two_rank_run_restarted_on_two_ranks(straight, tmp_path, mpiexec):
    out = tmp_path / "out"
    args = ["-m", "wrinkles", "run", str(DEFAULT), "--out", str(out)]
    assert mpiexec([*args, "--frames", "6"], n=2, timeout=300).returncode == 0
    proc = mpiexec([*args, "--frames", "10", "--restart"], n=2, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert len(progress_lines(proc.stdout)) == 4
    assert_same_run(straight, out, rtol=1e-6)  # Newton rtol 1e-9, another partition


@pytest.mark.mpi
def test_serial_checkpoint_restarted_on_two_ranks(straight, tmp_path, mpiexec):
    """The checkpoint is partition independent, and the XDMF series stays one series: the
    2-rank frames are appended in the serial file's node order (dolfinx wrote them in
    another one: the mesh inside a 2-rank step file is a permutation of the series' mesh),
    so every step reads like the straight serial run's."""
    out = tmp_path / "out"
    run_ok("--frames", "6", "--out", str(out))
    args = ["-m", "wrinkles", "run", str(DEFAULT), "--frames", "10", "--out", str(out),
            "--restart"]
    proc = mpiexec(args, n=2, timeout=300)
    assert proc.returncode == 0, proc.stderr
    with h5py.File(out / "body.h5", "r") as series, \
            h5py.File(out / "body.steps" / "step_000010.h5", "r") as step:
        stored, written = series["Mesh/mesh/geometry"][...], step["Mesh/mesh/geometry"][...]
    assert not np.array_equal(stored, written)
    assert node_order(stored, written) is not None
    assert_same_run(straight, out, rtol=1e-6)
    np.testing.assert_allclose(energies(out), energies(straight), rtol=1e-8)


@pytest.mark.parametrize(("setup", "extra", "pattern"), [
    ("none", [], r"^error: .*checkpoint\.h5: no checkpoint to restart from$"),
    ("run", ["--set", "material.E=6e4"],
     r"^error: --restart: the scene differs from the run in .* at 'material\.E' "),
    ("run", ["--set", "body.degree=2"],
     r"^error: --restart: the scene differs from the run in .* at 'body\.degree' "),
])
def test_restart_refuses_what_it_cannot_continue(tmp_path, setup, extra, pattern):
    out = tmp_path / "out"
    if setup == "run":
        run_ok("--frames", "2", "--out", str(out))
    proc = wrinkles("run", str(DEFAULT), "--frames", "4", "--out", str(out), "--restart", *extra)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert re.match(pattern, proc.stderr), proc.stderr


def test_restart_of_a_finished_run_says_so_and_one_past_it_is_refused(tmp_path):
    """Resuming a run for the frames it holds runs nothing and says so; for fewer frames than
    it holds it is refused, and the run on disk stays as it was."""
    out = tmp_path / "out"
    run_ok("--frames", "3", "--out", str(out))
    before = (out / "summary.json").read_text()
    stdout = run_ok("--frames", "3", "--out", str(out), "--restart")
    assert progress_lines(stdout) == [] and f"{out}: all 3 frames are done already" in stdout
    proc = wrinkles("run", str(DEFAULT), "--frames", "2", "--out", str(out), "--restart")
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1, proc.stderr
    assert re.match(r"^error: --resume: .* already holds 3 frames, more than the 2 asked",
                    proc.stderr), proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["frames"]) == 3 and summary["run"]["frames_planned"] == 3
    assert json.loads(before)["frames"] == summary["frames"]


def test_first_difference_names_the_dotted_key():
    from wrinkles.runner import first_difference

    old = {"time": {"frames": 2}, "body": {"dt": 0.01, "time": 1, "pins": [1, 2]}}
    assert first_difference(old, old) is None
    assert first_difference(old, {**old, "time": {"frames": 9}}, ignore=("time",)) is None
    changed = {**old, "body": {"dt": 0.01, "time": 2, "pins": [1, 2]}}
    assert first_difference(old, changed, ignore=("time",)) == "body.time"  # top level only
    assert first_difference(old, changed, ignore=("body.time",)) is None  # a dotted key
    assert first_difference(old, changed, ignore=("body.dt",)) == "body.time"
    assert first_difference(old, {**old, "extra": 1}) == "extra"


def test_node_order_matches_permuted_nodes_and_refuses_other_meshes(rng):
    """``node_order`` finds the permutation between two orders of the same nodes and refuses
    other node sets (one coordinate moved by 1e-12, a node missing, no geometry)."""
    stored = rng.random((50, 3))
    perm = rng.permutation(50)
    geometry = stored[perm]
    order = node_order(stored, geometry)
    assert order is not None and np.array_equal(geometry[order], stored)
    moved = geometry.copy()
    moved[3, 1] += 1e-12
    assert node_order(stored, moved) is None
    assert node_order(stored, geometry[:-1]) is None
    assert node_order(stored, None) is None


def test_reorder_fields_permutes_only_node_rows(tmp_path, rng):
    """Every ``/Function/*/*`` dataset with one row per node is permuted; others are kept."""
    path = tmp_path / "step.h5"
    values, other = rng.random((6, 3)), rng.random((4, 3))
    with h5py.File(path, "w") as h5:
        h5["Function/displacement/0_5"] = values
        h5["Function/other/0_5"] = other
        h5["Mesh/mesh/geometry"] = values
    order = np.array([5, 0, 4, 1, 3, 2])
    reorder_fields(path, order)
    with h5py.File(path, "r") as h5:
        np.testing.assert_array_equal(h5["Function/displacement/0_5"][...], values[order])
        np.testing.assert_array_equal(h5["Function/other/0_5"][...], other)
        np.testing.assert_array_equal(h5["Mesh/mesh/geometry"][...], values)
