"""The two-way joint system split over the ranks (solvers/decomposition/split_coupled.py).

tests/split_coupled_case.py under ``mpiexec``: the split energy, product and CG of a
two-way bar against the serial ones; and ``mpiexec -n N wrinkles run`` of that bar (5 762
shell vertices: the product splits its joint system) against the serial run.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from support import LENGTH, REPO, SKIN, bar_scene, dumps, wrinkles

from solvers.solver_choice import SPLIT_JOINT_FROM_VERTICES, choose_joint_split
from wrinkles.checkpoint import CHECKPOINT_NAME, read_state

SCRIPT = "tests/split_coupled_case.py"


def _result(proc) -> dict:
    assert proc.returncode == 0, f"rc={proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT "))
    return json.loads(line[len("RESULT "):])


@pytest.mark.mpi
@pytest.mark.parametrize("ranks", [2, 3])
def test_split_joint_system_equals_the_serial_one(mpiexec, ranks) -> None:
    """Value, gradient, diagonal, product and inner product to round-off (measured 2e-16 to
    3e-15 relative on 2 and 3 ranks); the CG solution passes the serial system's residual
    test at the same tolerance in as many iterations, within 2 (measured 32 against 33), and
    is the same on every rank."""
    out = _result(mpiexec([SCRIPT], n=ranks, timeout=300))
    print(out)
    assert out["joint_system"] == "split" and out["vertices"] >= SPLIT_JOINT_FROM_VERTICES
    assert out["shared_multigrid"]  # the split shell solver's multigrid is the shell block
    assert out["factorized"]
    for key in ("value_rel", "grad_rel", "diagonal_rel", "product_rel", "dot_rel"):
        assert out[key] < 1e-13, key
    assert out["residual"] < 2e-8  # CG tolerance 1e-8, the shell's residual slack
    assert abs(out["cg_iterations"][0] - out["cg_iterations"][1]) <= 2
    assert out["rank_spread"] == 0.0


def stretched_bar(tmp_path: Path, frames: int = 1) -> Path:
    shell = {"subdivision": {"levels": 3}, "skin": SKIN, "energy": {"k_P": 1.0e3},
             "solver": {"rtol": 1e-10, "max_iterations": 300},
             "imperfection": 0.0, "coupling": {"mode": "two_way"}}
    scene = tmp_path / "bar.toml"
    scene.write_text(dumps(bar_scene((0.04 * LENGTH, 0.0, 0.0), frames, shell)))
    return scene


@pytest.fixture(scope="module")
def serial_bar(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("serial")
    out = tmp / "out"
    proc = wrinkles("run", str(stretched_bar(tmp)), "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.mark.mpi
@pytest.mark.parametrize("ranks", [2, 3])
def test_split_two_way_run_equals_serial(serial_bar, mpiexec, tmp_path, ranks) -> None:
    """`mpiexec -n N wrinkles run` of the stretched two-way bar (a unique minimum) splits the
    joint system and reaches the serial frame: the same coupled Newton iterations, within
    one (measured equal: 12), energies to 1e-9 relative (measured 1e-13), the shell's positions
    and target (the body's surface) to 1e-9 of the bar's length (measured 7e-15 m)."""
    out = tmp_path / "out"
    proc = mpiexec(["-m", "wrinkles", "run", str(stretched_bar(tmp_path)), "--out", str(out)],
                   n=ranks, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "the two-way joint system split as well" in proc.stdout
    serial, split = (json.loads((o / "summary.json").read_text())["frames"][0]
                     for o in (serial_bar, out))
    print(serial["details"]["coupling_iterations"], split["details"]["coupling_iterations"],
          serial["energy"], split["energy"])
    assert serial["details"]["coupling_joint_system"] == "whole"
    assert split["details"]["coupling_joint_system"] == "split"
    assert split["details"]["coupling_converged"]
    assert abs(split["details"]["coupling_iterations"]
               - serial["details"]["coupling_iterations"]) <= 1
    assert split["energy"] == pytest.approx(serial["energy"], rel=1e-9)
    assert split["details"]["shell_energy"] == pytest.approx(
        serial["details"]["shell_energy"], rel=1e-9)
    states = [read_state(o / CHECKPOINT_NAME).arrays for o in (serial_bar, out)]
    for stage, name in (("shell", "positions"), ("shell", "target")):
        moved = float(np.abs(states[0][stage][name] - states[1][stage][name]).max())
        print(stage, name, moved)
        assert moved < 1e-9 * LENGTH


@pytest.mark.mpi
def test_split_two_way_run_resumed_on_one_rank_equals_the_straight_run(mpiexec,
                                                                       tmp_path) -> None:
    """Frame 1 on 2 ranks (the joint system split), then ``--resume`` on 1 rank to frame 2
    (whole): frame 2 of the straight serial run, the same coupled iterations within one,
    energies to 1e-9 and shell positions to 1e-9 of the bar's length (a unique minimum)."""
    scene = stretched_bar(tmp_path, frames=2)
    straight, out = tmp_path / "straight", tmp_path / "out"
    proc = wrinkles("run", str(scene), "--out", str(straight))
    assert proc.returncode == 0, proc.stderr
    proc = mpiexec(["-m", "wrinkles", "run", str(scene), "--out", str(out), "--frames", "1"],
                   n=2, timeout=300)
    assert proc.returncode == 0, proc.stderr
    proc = wrinkles("run", str(scene), "--out", str(out), "--resume")
    assert proc.returncode == 0, proc.stderr
    a, b = (json.loads((o / "summary.json").read_text())["frames"] for o in (straight, out))
    assert [r["details"]["coupling_joint_system"] for r in b] == ["split", "whole"]
    print([r["details"]["coupling_iterations"] for r in a + b], a[1]["energy"], b[1]["energy"])
    assert abs(a[1]["details"]["coupling_iterations"]
               - b[1]["details"]["coupling_iterations"]) <= 1
    assert b[1]["energy"] == pytest.approx(a[1]["energy"], rel=1e-9)
    states = [read_state(o / CHECKPOINT_NAME).arrays["shell"]["positions"]
              for o in (straight, out)]
    print("max shell difference", float(np.abs(states[0] - states[1]).max()))
    assert float(np.abs(states[0] - states[1]).max()) < 1e-9 * LENGTH


def test_joint_split_by_ranks_size_and_method() -> None:
    """Split on several ranks from the threshold with multigrid-CG; whole below it, on one
    rank, or on the direct path."""
    n = SPLIT_JOINT_FROM_VERTICES
    assert choose_joint_split(2, n, "multigrid")
    assert choose_joint_split(3, 10 * n, "multigrid")
    assert not choose_joint_split(2, n - 1, "multigrid")
    assert not choose_joint_split(1, 10 * n, "multigrid")
    assert not choose_joint_split(2, 10 * n, "direct")


@pytest.mark.parametrize(("scene", "levels", "expected"), [
    ("two_way_bar", 2, "whole"), ("two_way_bar", 3, "split"), ("default", 3, None)])
def test_check_names_how_two_ranks_hold_the_joint_system(scene, levels, expected) -> None:
    """``wrinkles check`` of a two-way scene says whether 2 ranks split its joint system:
    whole at the scene's 2 610 shell vertices, split at 3 levels (10 434); a one-way scene
    has no joint system."""
    proc = wrinkles("check", str(REPO / "scenes" / f"{scene}.toml"), "--set",
                    f"shell.subdivision.levels={levels}")
    assert proc.returncode == 0, proc.stderr
    shell = json.loads(proc.stdout)["resolved"]["shell"]
    assert shell.get("joint_system_on_2_ranks") == expected


@pytest.mark.mpi
def test_two_way_ball_on_sofa_on_two_ranks_equals_serial(mpiexec, tmp_path) -> None:
    """The demo scene two-way coupled (5 218 shell vertices: the joint system split; the ball,
    dynamics and contact on top), 5 frames through the ball's impact: on 2 ranks the serial
    coupled iterations frame by frame, within one (measured equal over 10 frames), energies
    to 1e-6 relative (measured 9e-9)."""
    scene = REPO / "scenes" / "ball_sofa_coarse.toml"
    args = ["--frames", "5", "--set", 'shell.coupling.mode="two_way"', "--set",
            "output.render=false"]
    serial, split = tmp_path / "serial", tmp_path / "split"
    proc = wrinkles("run", str(scene), "--out", str(serial), *args)
    assert proc.returncode == 0, proc.stderr
    proc = mpiexec(["-m", "wrinkles", "run", str(scene), "--out", str(split), *args], n=2,
                   timeout=300)
    assert proc.returncode == 0, proc.stderr
    a, b = (json.loads((o / "summary.json").read_text())["frames"] for o in (serial, split))
    assert [r["details"]["coupling_joint_system"] for r in b] == ["split"] * 5
    for x, y in zip(a, b, strict=True):
        print(x["frame"], x["details"]["coupling_iterations"], y["details"]["coupling_iterations"],
              x["energy"], y["energy"])
        assert abs(x["details"]["coupling_iterations"] - y["details"]["coupling_iterations"]) <= 1
        assert y["energy"] == pytest.approx(x["energy"], rel=1e-6)
        assert y["details"]["shell_energy"] == pytest.approx(x["details"]["shell_energy"],
                                                             rel=1e-6)


@pytest.mark.mpi
def test_a_failed_split_joint_solve_ends_every_rank_as_the_serial_run(mpiexec, tmp_path) -> None:
    """The stretched bar's coupled solve capped at 2 Newton iterations (it needs 12): every
    split solve fails, the body halves its step to the limit, and both ranks end with exit 2
    and the serial run's one line on stderr (up to the last residual's round-off), the same
    failure in ``summary.json``; no hang."""
    scene = stretched_bar(tmp_path)
    args = ["run", str(scene), "--set", "shell.solver.max_iterations=2"]
    outs = {"serial": tmp_path / "serial", "split": tmp_path / "split"}
    serial = wrinkles(*args, "--out", str(outs["serial"]))
    split = mpiexec(["-m", "wrinkles", *args, "--out", str(outs["split"])], n=2, timeout=300)
    lines = {}
    for name, proc in (("serial", serial), ("split", split)):
        assert proc.returncode == 2, proc.stderr[-2000:]
        errors = [line for line in proc.stderr.splitlines() if not line.startswith("warning")]
        assert len(errors) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
        lines[name] = errors[0]
    print(lines["split"])
    assert lines["split"].startswith("error: body step failed at t=0 after")
    # the same line up to the last coupled residual, which differs by round-off (4.848e-04
    # against 4.850e-04 measured)
    assert lines["split"].split(", residual=")[0] == lines["serial"].split(", residual=")[0]
    runs = [json.loads((outs[n] / "summary.json").read_text())["run"] for n in outs]
    assert runs[0]["status"] == runs[1]["status"] and runs[0]["failed_frame"] == \
        runs[1]["failed_frame"] == 1
