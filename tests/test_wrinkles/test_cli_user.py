"""The run as a user touches it: no run clobbered, strict summary, version, errors that are the
user's reported as such."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
from support import DEFAULT_SCENE, DROP_BLOCK, SCENE, wrinkles

from wrinkles.output import json_text, strict
from wrinkles.shell_setup import BYTES_PER_VERTEX, shell_vertices

TWO = ("--frames", "2")


def test_a_new_run_into_a_used_directory_is_refused_and_leaves_it_intact(tmp_path):
    out = tmp_path / "out"
    assert wrinkles("run", str(DROP_BLOCK), "--out", str(out), *TWO).returncode == 0
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    summary = (out / "summary.json").read_text()
    proc = wrinkles("run", str(DROP_BLOCK), "--out", str(out), "--frames", "1")
    assert proc.returncode == 1
    assert f"--out {out}: holds another run" in proc.stderr and "--overwrite" in proc.stderr
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    assert (out / "summary.json").read_text() == summary


def test_overwrite_replaces_the_run_and_keeps_other_files(tmp_path):
    out = tmp_path / "out"
    assert wrinkles("run", str(DROP_BLOCK), "--out", str(out), *TWO).returncode == 0
    (out / "notes.txt").write_text("mine")
    proc = wrinkles("run", str(DROP_BLOCK), "--out", str(out), "--frames", "1", "--overwrite")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["frames"]) == 1 and summary["run"]["status"] == "completed"
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / ".work").exists()


def test_a_run_refused_at_set_up_writes_nothing(tmp_path):
    """A shell that cannot be built (here: too large for the machine) is refused before the
    first file is written, and the exit is a one-line bad-input error. The output directory
    the run created is gone again; one the user had stays."""
    too_large = ("--set", "shell.subdivision.levels=12")
    out = tmp_path / "out"
    proc = wrinkles("run", str(DEFAULT_SCENE), "--out", str(out), *too_large)
    assert proc.returncode == 1, proc.stderr
    assert "shell.subdivision.levels = 12: the shell would have about" in proc.stderr
    assert "GiB available" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    assert wrinkles("run", str(DEFAULT_SCENE), "--out", str(mine), *too_large).returncode == 1
    assert mine.is_dir() and not any(mine.iterdir())


def test_memory_estimate_of_the_levels():
    assert shell_vertices(12, 0) == 8 and shell_vertices(12, 1) == 26  # a cube's octahedron..
    assert shell_vertices(20, 2) == 162  # the icosahedron subdivided twice
    assert BYTES_PER_VERTEX["direct"] > BYTES_PER_VERTEX["multigrid"]


def test_unwritable_output_is_bad_input(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    proc = wrinkles("run", str(DROP_BLOCK), "--out", str(blocker / "out"), *TWO)
    assert proc.returncode == 1
    assert "--out" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_summary_is_strict_json_with_provenance(tmp_path):
    out = tmp_path / "out"
    assert wrinkles("run", str(DROP_BLOCK), "--out", str(out), *TWO).returncode == 0
    text = (out / "summary.json").read_text()
    summary = json.loads(text, parse_constant=lambda token: pytest.fail(f"token {token}"))
    run = summary["run"]
    assert run["command"].split()[-4:] == ["--out", str(out), "--frames", "2"]
    assert run["wall_time"] > 0 and run["status"] == "completed"
    assert "commit" in run and summary["versions"]["wrinkles"]


def test_strict_spells_non_finite_numbers_as_strings():
    data = {"a": math.inf, "b": [-math.inf, math.nan, 1.5], "c": {"d": float("nan")}}
    assert strict(data) == {"a": "inf", "b": ["-inf", "nan", 1.5], "c": {"d": "nan"}}
    assert json.loads(json_text(data))["a"] == "inf"


def test_version():
    proc = wrinkles("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("wrinkles 0.")


def test_resume_and_overwrite_exclude_each_other(tmp_path):
    proc = wrinkles("run", str(DROP_BLOCK), "--out", str(tmp_path), "--resume", "--overwrite")
    assert proc.returncode == 1 and "exclude each other" in proc.stderr


@pytest.mark.parametrize("levels", [0])
def test_check_prints_the_values_the_run_uses(levels):
    """With a [shell.skin] the stiffnesses come from the skin: ``check`` prints those (and
    the shell's size), not the energy table's defaults."""
    proc = wrinkles("check", str(DEFAULT_SCENE), "--set", f"shell.subdivision.levels={levels}")
    assert proc.returncode == 0, proc.stderr
    resolved = json.loads(proc.stdout)["resolved"]
    shell = resolved["shell"]
    assert shell["vertices"] == 165 and shell["mean_edge_length"] > 0  # 326 faces at level 0
    # D / 6 = E h^3 / (72 (1 - nu^2)) of the 50 MPa, 0.5 mm skin (cylinder calibration)
    assert shell["k_B"] == pytest.approx(5.0e7 * 5.0e-4**3 / (72.0 * (1.0 - 0.3**2)), rel=1e-12)
    assert shell["k_L"] != 1e3 and shell["clusters"]["spacing"] > 0
    assert shell["internals"]["energy.penalty_hessian"] == "low_rank"
    assert resolved["mesh"]["tets"] == 431 and resolved["mesh"]["source"].startswith("box(")


def test_progress_announces_set_up_and_shows_the_shell_and_the_load(tmp_path):
    proc = wrinkles("run", str(DEFAULT_SCENE), "--out", str(tmp_path / "out"), "--frames", "2",
                    "--set", "shell.subdivision.levels=0", "--set", "output.render=false")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    set_up = [k for k, line in enumerate(lines) if line.startswith("set-up: ")]
    frames = [k for k, line in enumerate(lines) if line.startswith("frame ")]
    assert len(frames) == 2 and set_up and max(set_up) < min(frames)
    assert any("vertices" in lines[k] for k in set_up)
    assert any("clusters" in lines[k] for k in set_up)
    for k in frames:  # a static scene: the load parameter, and the shell's iterations
        assert " load= 0." in lines[k] and " t=" not in lines[k]
        assert " shell=" in lines[k] and " its " in lines[k]


def test_warnings_name_the_keys_a_user_changes(tmp_path):
    """A shell too coarse for its skin's wrinkles and a pin that holds one node are warned
    about on one line each, naming the scene keys."""
    proc = wrinkles("run", str(DEFAULT_SCENE), "--out", str(tmp_path / "a"), "--frames", "1",
                    "--set", "shell.subdivision.levels=0", "--set", "output.render=false")
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("warning: ")]
    assert any("shell.subdivision.levels = 0: the skin's wrinkle wavelength" in ln
               for ln in lines)
    assert any(ln.startswith("warning: shell.clusters: the median cluster holds") for ln in lines)
    pin = 'body.pins=[{box=[[0.0, 0.0, 0.02], [0.0, 0.0, 0.02]], tol=1e-9}]'
    proc = wrinkles("run", str(DROP_BLOCK), "--out", str(tmp_path / "b"), "--frames", "1",
                    "--set", pin)
    assert proc.returncode == 0, proc.stderr
    assert "warning: body.pins[0]: holds only 1 node(s)" in proc.stderr
    assert "pins hold 1 nodes" in proc.stdout


def test_up_axis_sets_gravity_and_plane_normals_unless_written(tmp_path):
    from wrinkles.scene import load_scene, scene_dict

    text = DROP_BLOCK.read_text().replace('title = "', 'up = "y"\ntitle = "', 1)
    text = "\n".join(ln for ln in text.splitlines()
                     if not ln.startswith(("gravity", "normal")))
    path = tmp_path / "yup.toml"
    path.write_text(text)
    body = scene_dict(load_scene(path))["body"]
    assert body["gravity"] == [0.0, -9.81, 0.0]
    assert body["contacts"][0]["normal"] == [0.0, 1.0, 0.0]
    written = scene_dict(load_scene(path, ["body.gravity=[0.0, 0.0, -1.0]"]))["body"]
    assert written["gravity"] == [0.0, 0.0, -1.0]
    with pytest.raises(Exception, match="up: must be one of"):
        load_scene(path, ["up=w"])


def test_a_ball_starting_inside_the_body_is_refused(tmp_path):
    ball = 'rigid.balls=[{radius=0.15, mass=5.0, center=[1.0, 0.35, 0.3]}]'
    proc = wrinkles("run", str(SCENE), "--out", str(tmp_path / "out"), "--frames", "1",
                    "--set", ball)
    assert proc.returncode == 1
    assert "rigid.balls[0].center = [1.0, 0.35, 0.3]: inside the body" in proc.stderr


def test_a_static_scene_without_pins_is_warned_about(tmp_path):
    proc = wrinkles("run", str(DROP_BLOCK), "--out", str(tmp_path / "out"), "--frames", "1",
                    "--set", 'body.dynamics="static"', "--set", "body.dt=0.5")
    assert "warning: body.pins: a static scene without pins has no unique solution" in proc.stderr
    assert proc.returncode == 2  # and the solve fails, as the warning says


def test_a_set_key_that_adds_a_shell_to_a_body_only_scene_is_warned_about(tmp_path):
    """``drop_block.toml`` has no [shell]: a ``--set shell.*`` key adds one, and says so."""
    proc = wrinkles("check", str(DROP_BLOCK), "--set", "shell.imperfection_seed=2")
    assert proc.returncode == 0, proc.stderr
    assert ("warning: --set shell.imperfection_seed: drop_block.toml has no [shell] table; the "
            "override adds one" in proc.stderr)
    assert json.loads(proc.stdout)["scene"]["shell"] is not None
    quiet = wrinkles("check", str(DEFAULT_SCENE), "--set", "shell.imperfection_seed=2")
    assert quiet.returncode == 0 and "no [shell] table" not in quiet.stderr


LIGHT_CLI = """
import sys
from wrinkles.cli import build_parser
build_parser()
heavy = ("numba", "scipy", "gmsh", "dolfinx", "mpi4py", "petsc4py", "pyvista", "matplotlib")
print(sorted(m for m in heavy if m in sys.modules))
"""


def test_the_cli_starts_without_the_solvers_stack():
    """``wrinkles --help``, ``view``, ``plot`` and ``render`` parse their arguments before any
    of numba, scipy, gmsh, the FE stack or the plotting libraries loads (each command loads
    what it uses)."""
    done = subprocess.run([sys.executable, "-c", LIGHT_CLI], capture_output=True, text=True,
                          timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
