"""A serial ``wrinkles run`` of a large frame (shell, or body under a smaller shell) runs on
the machine's cores as MPI ranks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import DEFAULT_SCENE, EXTERNAL_MESHES, REPO, load_script, wrinkles

from solvers import solver_choice
from solvers.solver_choice import RANKS_FROM_WORK, available_cores
from wrinkles import cli
from wrinkles.launch import LAUNCHER_VARIABLES, mpiexec_beside, under_launcher
from wrinkles.scene import load_scene

LEVELS_3 = ["--set", "shell.subdivision.levels=3"]
"""The default bar at three subdivision levels: 10 434 shell vertices, over the crossover."""
SMALL_LOAD = ["--frames", "1", "--set", "body.dt=0.01", "--set", "output.render=false"]
"""One frame of a 0.2 mm push: the skin does not buckle, the frame takes a few seconds."""


def scene(*overrides: str):
    """The default scene with ``--set`` overrides (``key=value`` strings)."""
    return load_scene(DEFAULT_SCENE, list(overrides))


@pytest.fixture
def two_cores(monkeypatch):
    """A machine of two cores with the wheel's launcher, the process started without MPI."""
    monkeypatch.setattr(solver_choice, "available_cores", lambda: 2)
    monkeypatch.setattr(cli, "mpiexec_beside", lambda: "/venv/bin/mpiexec")
    for name in LAUNCHER_VARIABLES:
        monkeypatch.delenv(name, raising=False)


def test_the_default_scene_stays_in_one_process_at_three_levels_it_takes_two_ranks(two_cores):
    assert cli.command_ranks(scene())[0] == 1  # 2 610 vertices + 516 body dofs
    ranks, why = cli.command_ranks(scene("shell.subdivision.levels=3"))
    assert (ranks, why) == (2, "10434 shell vertices + 516 body dofs x 1 step(s), 2 cores")
    assert 2610 + 516 < RANKS_FROM_WORK <= 10434 + 516


@pytest.mark.skipif(not EXTERNAL_MESHES.is_dir(), reason="../shared/meshes_external missing")
def test_a_large_body_under_a_small_shell_takes_two_ranks(two_cores, tmp_path):
    """The cinolib ball dropped (``benchmarks/external_meshes.py``'s scene: 13 515 body dofs
    x 2 steps under 5 762 shell vertices) goes; the elbow closing (5 469 x 1 + 3 358) stays."""
    scene_text = load_script(REPO / "benchmarks" / "external_meshes.py").scene_text
    path = tmp_path / "ball.toml"
    path.write_text(scene_text(EXTERNAL_MESHES / "cinolib_sphere.mesh", "z", 4))
    ranks, why = cli.command_ranks(load_scene(path))
    assert (ranks, why) == (2, "5762 shell vertices + 13515 body dofs x 2 step(s), 2 cores")
    assert cli.command_ranks(load_scene(REPO / "scenes" / "elbow_closing.toml"))[0] == 1


@pytest.mark.skipif(not EXTERNAL_MESHES.is_dir(), reason="../shared/meshes_external missing")
def test_a_large_body_without_a_shell_takes_two_ranks(two_cores, tmp_path, capsys):
    """The cinolib ball dropped without its skin (13 515 body dofs x 2 steps) goes, by the same
    work as under a shell; the falling block (1 260 x 1) stays; `wrinkles check` says so."""
    text = load_script(REPO / "benchmarks" / "external_meshes.py").scene_text(
        EXTERNAL_MESHES / "cinolib_sphere.mesh", "z", 4)
    path = tmp_path / "ball.toml"
    path.write_text(text[:text.index("[shell]")])
    ball = load_scene(path)
    assert ball.shell is None
    assert cli.command_ranks(ball) == (2, "13515 body dofs x 2 step(s), 2 cores")
    assert cli.command_ranks(load_scene(REPO / "scenes" / "drop_block.toml"))[0] == 1
    assert cli.one_process(ball) == "mpiexec -n 1 wrinkles run ..."  # no shell key to name
    assert cli.one_process(scene()) == "--set shell.solver.threads=1"
    capsys.readouterr()
    assert cli.main(["check", str(path)]) == 0
    assert json.loads(capsys.readouterr().out)["resolved"]["ranks_of_a_serial_run"] == 2


def test_named_threads_or_a_launcher_keep_one_process_a_two_way_shell_goes(two_cores,
                                                                           monkeypatch):
    assert cli.command_ranks(scene("shell.subdivision.levels=3",
                                   "shell.solver.threads=1"))[0] == 1
    assert cli.command_ranks(scene("shell.subdivision.levels=3",
                                   "shell.coupling.mode='two_way'"))[0] == 2
    monkeypatch.setenv("PMI_SIZE", "1")  # mpiexec -n 1 wrinkles run: the user chose one rank
    assert cli.command_ranks(scene("shell.subdivision.levels=3"))[0] == 1


def test_without_the_wheels_launcher_or_a_second_core_the_run_stays(two_cores, monkeypatch):
    big = scene("shell.subdivision.levels=3")
    monkeypatch.setattr(cli, "mpiexec_beside", lambda: None)
    assert cli.command_ranks(big)[0] == 1
    monkeypatch.setattr(cli, "mpiexec_beside", lambda: "/venv/bin/mpiexec")
    monkeypatch.setattr(solver_choice, "available_cores", lambda: 1)
    assert cli.command_ranks(big)[0] == 1


def test_many_cores_give_one_rank_per_five_thousand_vertices_and_overlap_two(monkeypatch):
    monkeypatch.setattr(solver_choice, "available_cores", lambda: 16)
    monkeypatch.setattr(cli, "mpiexec_beside", lambda: "/venv/bin/mpiexec")
    for name in LAUNCHER_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    assert cli.command_ranks(scene("shell.subdivision.levels=4"))[0] == 8  # 41 730 vertices
    assert cli.command_ranks(scene("shell.subdivision.levels=4",
                                   "shell.solver.layout='overlap'"))[0] == 2


def test_launcher_variables_are_recognised():
    assert under_launcher({"PMI_SIZE": "2", "PMI_RANK": "0"})
    assert under_launcher({"OMPI_COMM_WORLD_SIZE": "4"})
    assert not under_launcher({"PATH": "/usr/bin", "SLURM_JOB_ID": "7"})


DECIDE_WITHOUT_STACK = """
import sys
from wrinkles.cli import command_ranks
from wrinkles.overlap import scene_sizes
from wrinkles.scene import load_scene
scene = load_scene(sys.argv[1], ["shell.subdivision.levels=3", "rigid.balls=[]"])
print(scene_sizes(scene).work, command_ranks(scene)[0] >= 1)
print(sorted(m for m in ("dolfinx", "mpi4py", "petsc4py", "ufl") if m in sys.modules))
"""
"""Load a scene with a warning, size it, decide its ranks; print which stack modules loaded."""


def test_the_rank_decision_loads_no_fe_stack_and_no_mpi():
    """A serial command decides whether to go on to ranks before dolfinx loads or MPI starts:
    the relaunch pays the scene's own imports only (models.backend loads the stack on use)."""
    done = subprocess.run([sys.executable, "-c", DECIDE_WITHOUT_STACK, str(DEFAULT_SCENE)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["10950 True", "[]"]  # 10 434 vertices + 516 dofs
    assert "has no [rigid] table" in done.stderr


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


@pytest.mark.skipif(available_cores() < 2 or mpiexec_beside() is None,
                    reason="needs two cores and the wheel's mpiexec")
def test_the_command_goes_on_two_ranks_and_agrees_with_one_process(tmp_path):
    auto = wrinkles("run", str(DEFAULT_SCENE), "--out", str(tmp_path / "auto"),
                    *LEVELS_3, *SMALL_LOAD, "--set", "rigid.balls=[]")
    assert auto.returncode == 0, auto.stderr
    assert "10434 shell vertices + 516 body dofs x 1 step(s), 2 cores: running on 2 MPI ranks" \
        in auto.stdout
    assert auto.stderr.count("has no [rigid] table") == 1  # said by the ranks, not twice
    one = wrinkles("run", str(DEFAULT_SCENE), "--out", str(tmp_path / "one"), *LEVELS_3,
                   *SMALL_LOAD, "--set", "shell.solver.threads=1")
    assert one.returncode == 0, one.stderr
    assert "MPI ranks" not in one.stdout
    ranks, serial = summary(tmp_path / "auto"), summary(tmp_path / "one")
    assert (ranks["run"]["ranks"], serial["run"]["ranks"]) == (2, 1)
    assert ranks["run"]["command"].split()[1:3] == ["run", str(DEFAULT_SCENE)]
    np.testing.assert_allclose(ranks["frames"][0]["energy"], serial["frames"][0]["energy"],
                               rtol=1e-9)  # the body's energy (Newton rtol 1e-9)
    w2, w1 = (s["frames"][0]["details"]["shell_energy"] for s in (ranks, serial))
    assert w1 > 0 and abs(w2 - w1) <= 1e-6 * w1  # to the Newton tolerance (measured 2e-15)
    assert ranks["frames"][0]["details"]["shell_converged"] is True
    assert (tmp_path / "auto" / "shell.xdmf").is_file()
