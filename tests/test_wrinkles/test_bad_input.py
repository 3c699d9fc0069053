"""Bad input is refused with exit code 1 and one line naming the file, key or element.

Scene files, mesh files and command-line misuse go through ``wrinkles.cli.main`` in process;
each case asserts the exit code, that stderr is exactly one ``error: ...`` line without a
traceback, and that it names what is wrong. The 2-rank cases check that the same refusals do
not deadlock under MPI (``mpiexec`` fixture, timeout).
"""

from __future__ import annotations

import json
import math
import re
import warnings
from pathlib import Path
from typing import Any

import meshio
import numpy as np
import pytest
from support import REPO, base_scene, cube_tets, dumps

import wrinkles.cli as cli

DEFAULT = REPO / "scenes" / "drop_block.toml"  # the falling block (default.toml: wrinkles)











def set_key(doc: dict[str, Any], dotted: str, value: Any) -> dict[str, Any]:
    """Set (or with ``...`` delete) a dotted key of a nested dict in place; return it."""
    *path, last = dotted.split(".")
    table = doc
    for part in path:
        table = table.setdefault(part, {})
    if value is ...:
        table.pop(last, None)
    else:
        table[last] = value
    return doc


def write_scene(tmp_path: Path, doc: dict[str, Any], name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(dumps(doc))
    return path


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    """Run ``wrinkles ARGV`` in process; return the exit code and stderr."""
    code = cli.main(list(argv))
    return code, capsys.readouterr().err


def assert_refused(code: int, err: str, *names: str) -> None:
    """Exit 1, one ``error:`` line, no traceback, every name in the message."""
    assert code == 1, err
    assert err.count("\n") == 1 and err.startswith("error: ") and "Traceback" not in err, err
    for name in names:
        assert name in err, (name, err)


SCENE_CASES: list[tuple[str, Any, tuple[str, ...]]] = [
    ("materal.E", 1.0, ("materal",)),                                # unknown table
    ("material.Young", 1.0, ("material.Young",)),                    # unknown key
    ("body.pins", [{"colour": 1}], ("colour",)),     # unknown nested key
    ("material.E", "soft", ("material.E",)),                         # wrong type
    ("material.E", -1.0, ("E",)),                                    # negative
    ("material.E", math.nan, ("E",)),                                # NaN
    ("material.nu", 0.5, ("nu",)),                                   # incompressible limit
    ("material.nu", -1.5, ("nu",)),
    ("material.density", math.inf, ("density",)),
    ("material.model", "rubber", ("model",)),
    ("body.dt", 0.0, ("body.dt",)),
    ("body.dt", -1e-3, ("body.dt",)),
    ("body.degree", 3, ("body.degree",)),
    ("body.gravity", [0.0, 9.81], ("gravity",)),
    ("body.pins", [{"normal": [0.0, 0.0, 0.0]}], ("normal",)),
    ("body.pins", [{"components": [0, 0]}], ("components",)),
    ("body.contacts", [{"obstacle": "torus"}], ("obstacle",)),
    ("newton.options", {"max_it": 0}, ("max_it",)),
    ("newton.rtol", math.nan, ("newton.rtol",)),
    ("newton.options", {"linear_solver": "umfpack"}, ("linear_solver",)),
    ("newton.options", {"petsc": {"ksp_rtoll": 1e-9}}, ("newton.options.petsc.ksp_rtoll",)),
    ("newton.options", {"petsc": {"pc_type": "hypre"}}, ("PC type hypre",)),
    ("time.frames", 0, ("frames",)),
    ("time.end_time", 1.0, ("time.end_time", "time.frames")),        # retired key
    ("time.steps_per_frame", -2, ("steps_per_frame",)),
    ("output.every", 0, ("output.every",)),
    ("mesh.file", "body.vtu", ("mesh",)),                            # builder and file
    ("mesh.builder", "teapot", ("mesh.builder",)),
    ("mesh.params", {"lx": 0.1, "radius": 2.0}, ("radius",)),
    ("mesh.params", {"lx": "wide", "ly": 0.1, "lz": 0.1, "h": 0.05}, ("lx",)),
    ("shell.solver.threads", -1, ("shell.solver.threads",)),
    ("shell.solver.threads", 1.5, ("shell.solver.threads",)),
    ("shell.solver.options", {"newton.shift.growht": 5}, ("shell.solver.options.newton.shift",
                                                          "growth")),
    ("shell.energy.k_B", -1.0, ("shell.energy.k_B",)),
    ("up", [], ("up",)),                                             # found by the fuzz test
    ("up", "w", ("up", "'x', 'y', 'z'")),
]


@pytest.mark.parametrize(("key", "value", "names"), SCENE_CASES,
                         ids=[f"{k}={v!r}"[:40] for k, v, _ in SCENE_CASES])
def test_bad_scene_value_refused_by_check(tmp_path, capsys, key, value, names):
    path = write_scene(tmp_path, set_key(base_scene(), key, value))
    code, err = run_cli(capsys, "check", str(path))
    assert_refused(code, err, "scene.toml", *names)


@pytest.mark.parametrize(("override", "names"), [
    ("output.xdmf=false", ("output.render = true", "output.xdmf = false")),  # nothing to draw
    ("shell.solver.layout='both'", ("shell.solver.layout",)),
])
def test_bad_shell_output_or_layout_refused_by_check(capsys, override, names):
    """On the demo scene (a shell, ``output.render = true``)."""
    code, err = run_cli(capsys, "check", str(REPO / "scenes" / "ball_sofa_coarse.toml"),
                        "--set", override)
    assert_refused(code, err, "ball_sofa_coarse.toml", *names)


def test_missing_scene_table_value_uses_no_default_silently(tmp_path, capsys):
    """A scene without ``[mesh]`` cannot run: refused naming the missing table."""
    path = write_scene(tmp_path, set_key(base_scene(), "mesh", ...))
    code, err = run_cli(capsys, "check", str(path))
    assert_refused(code, err, "mesh")


@pytest.mark.parametrize(("text", "names"), [
    ("[material\nE = 1", ("scene.toml",)),                 # TOML syntax error
    ("title = 'a'\ntitle = 'b'\n", ("scene.toml",)),        # duplicate key
    ("\x00\x01binary", ("scene.toml",)),
])
def test_unparsable_scene_file_refused(tmp_path, capsys, text, names):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    assert_refused(*run_cli(capsys, "check", str(path)), *names)


@pytest.mark.parametrize("argv", [
    ["check", "{tmp}/absent.toml"],
    ["check", "{tmp}"],                                    # a directory
    ["run", "{tmp}/absent.toml", "--out", "{tmp}/out"],
])
def test_missing_scene_file_refused(tmp_path, capsys, argv):
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert_refused(*run_cli(capsys, *argv), str(Path(argv[1]).name))


@pytest.mark.parametrize(("argv", "names"), [
    ([], ("required",)),
    (["simulate", "x.toml"], ("simulate",)),
    (["run"], ("scene",)),
    (["run", "{scene}", "--frames", "many"], ("--frames", "many")),
    (["run", "{scene}", "--frames", "0"], ("--frames",)),
    (["run", "{scene}", "--frames", "-3"], ("--frames",)),
    (["run", "{scene}", "--fast"], ("--fast",)),
    (["check", "{scene}", "--set", "material.E"], ("material.E",)),
    (["check", "{scene}", "--set", "material.E=soft rubber"], ("material.E",)),
    (["check", "{scene}", "--set", "material.E=-5"], ("E",)),
    (["check", "{scene}", "--set", "nothing.here=1"], ("nothing",)),
    (["run", "{scene}", "--out", "{tmp}/empty", "--resume"], ("checkpoint.h5",)),
    (["run", "{scene}", "--out", "{file}"], ("--out",)),     # out is a file
])
def test_cli_misuse_refused(tmp_path, capsys, argv, names):
    scene = write_scene(tmp_path, base_scene())
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    argv = [a.format(scene=scene, tmp=tmp_path, file=blocker / "sub") for a in argv]
    names = tuple(n.format(tmp=tmp_path) for n in names)
    assert_refused(*run_cli(capsys, *argv), *names)


# --------------------------------------------------------------------------------------------
# Mesh files




def mesh_case(kind: str) -> tuple[np.ndarray, list[tuple[str, np.ndarray]]]:
    """Points and meshio cell blocks of a broken mesh."""
    points, tets = cube_tets()
    if kind == "flat":                              # all four corners of tet 2 in one plane
        points = np.vstack([points, [[0.05, 0.05, 0.0]]])
        tets = np.vstack([tets, [[0, 1, 2, 8]]])
    elif kind == "duplicated":
        tets = np.vstack([tets, tets[3:4, [1, 0, 3, 2]]])
    elif kind == "vertex_nonmanifold":              # a second cube touching at one corner
        tets = np.vstack([tets, tets + 8 - 1])
        points = np.vstack([points, points[1:] + points[7]])
    elif kind == "huge":
        points = points * 1e12
    elif kind == "nan":
        points[5, 1] = np.nan
    elif kind == "empty":
        return points, []
    elif kind == "vertices":
        return points, [("vertex", np.arange(8)[:, None])]
    elif kind == "triangles":
        return points, [("triangle", np.array([[0, 1, 3], [0, 3, 2]]))]
    elif kind == "out_of_range":
        tets = tets.copy()
        tets[4, 2] = 99
    return points, [("tetra", tets)]


MESH_CASES: list[tuple[str, tuple[str, ...]]] = [
    ("flat", ("degenerate",)),
    ("duplicated", ("duplicate",)),
    ("vertex_nonmanifold", ("vertex",)),
    ("huge", ("coordinate",)),
    ("nan", ("point 5",)),
    ("empty", ()),  # meshio cannot even read a .vtu without cells: named as unreadable
    ("vertices", ("no tetrahedra", "vertex")),
    ("triangles", ("no tetrahedra", "triangle")),
    ("out_of_range", ("99",)),
]


@pytest.mark.parametrize(("kind", "names"), MESH_CASES, ids=[k for k, _ in MESH_CASES])
def test_bad_mesh_file_refused_by_run(tmp_path, capsys, kind, names):
    points, cells = mesh_case(kind)
    meshio.write_points_cells(tmp_path / "body.vtu", points, cells)
    doc = set_key(base_scene(), "mesh", {"file": "body.vtu"})
    scene = write_scene(tmp_path, doc)
    code, err = run_cli(capsys, "run", str(scene), "--out", str(tmp_path / "out"))
    assert_refused(code, err, "body.vtu", *names)
    assert not (tmp_path / "out" / "summary.json").exists()


def test_garbage_mesh_file_refused(tmp_path, capsys):
    (tmp_path / "body.msh").write_text("$MeshFormat\n4.1 0 8\ngarbage\n")
    scene = write_scene(tmp_path, set_key(base_scene(), "mesh", {"file": "body.msh"}))
    assert_refused(*run_cli(capsys, "run", str(scene), "--out", str(tmp_path / "out")),
                   "body.msh")


def test_missing_mesh_file_refused_by_check(tmp_path, capsys):
    scene = write_scene(tmp_path, set_key(base_scene(), "mesh", {"file": "nowhere.vtu"}))
    assert_refused(*run_cli(capsys, "check", str(scene)), "nowhere.vtu")


def test_inverted_mesh_is_repaired_with_a_warning_and_runs(tmp_path, capsys):
    """Inverted tets are the one defect that is repaired (documented): the run succeeds."""
    points, tets = cube_tets()
    results = []
    for name, cells in (("good", tets), ("inverted", tets[:, [0, 2, 1, 3]])):
        meshio.write_points_cells(tmp_path / f"{name}.vtu", points, [("tetra", cells)])
        doc = set_key(base_scene(), "mesh", {"file": f"{name}.vtu"})
        scene = write_scene(tmp_path, doc, f"{name}.toml")
        with pytest.warns(UserWarning, match="inverted.vtu") if name == "inverted" else \
                warnings.catch_warnings():
            code, err = run_cli(capsys, "run", str(scene), "--out", str(tmp_path / name))
        assert code == 0, err
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert summary["run"]["status"] == "completed"
        results.append(summary["frames"][0])
    print("good vs repaired:", [(r["energy"], r["min_det_f"]) for r in results])
    assert results[1]["energy"] == pytest.approx(results[0]["energy"], rel=1e-10)
    assert results[1]["min_det_f"] == pytest.approx(results[0]["min_det_f"], rel=1e-10)
    assert results[0]["min_det_f"] < 1.0  # it did deform: sag under gravity


def command(name: str, scene: Path, out: Path) -> list[str]:
    """argv of ``wrinkles run SCENE --out OUT`` or ``wrinkles check SCENE``."""
    return ["run", str(scene), "--out", str(out)] if name == "run" else ["check", str(scene)]


@pytest.mark.parametrize("name", ["run", "check"])
def test_pin_selecting_no_node_refused(tmp_path, capsys, name):
    """The message names the pin's region and the span of the mesh's nodes (the 10 cm box)."""
    doc = set_key(base_scene(), "body.pins", [{"point": [0.0, 0.0, 5.0]}])
    scene = write_scene(tmp_path, doc)
    assert_refused(*run_cli(capsys, *command(name, scene, tmp_path / "out")),
                   "body.pins[0]: the plane through (0, 0, 5) with normal (0, 0, 1) (tol 1e-08 m)",
                   "selects no node", "x 0 .. 0.1, y 0 .. 0.1, z 0 .. 0.1 m")


ROLLERS = [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "tol": 1e-6, "components": [2]}]
"""The base cube's bottom face held in z only: free to slide in x and y and to turn about z."""
FREE_WARNING = ("warning: body.pins: the pins of this static scene leave 3 rigid motion(s) of "
                "the body free (translation along x, translation along y, rotation about z)")


@pytest.mark.parametrize("name", ["run", "check"])
@pytest.mark.parametrize(("pins", "dynamics", "warned"), [
    (ROLLERS, "static", True), (ROLLERS, "implicit_euler", False), (None, "static", False)])
def test_pins_leaving_rigid_motions_free_are_warned_about(tmp_path, capsys, name, pins,
                                                          dynamics, warned):
    """In statics only (inertia holds a dynamic body); the base scene's clamped face holds
    all six motions."""
    doc = set_key(base_scene(), "body.dynamics", dynamics)
    if pins is not None:
        set_key(doc, "body.pins", pins)
    scene = write_scene(tmp_path, doc)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, err = run_cli(capsys, *command(name, scene, tmp_path / "out"))
    assert code == 0, err
    said = [str(w.message) for w in caught]
    assert any(FREE_WARNING.removeprefix("warning: ") in m for m in said) == warned, said


@pytest.mark.mpi
def test_free_rigid_motions_are_found_over_the_ranks_nodes(tmp_path, mpiexec):
    """On two ranks the body's nodes are split: the same warning, once."""
    scene = write_scene(tmp_path, set_key(base_scene(), "body.pins", ROLLERS))
    proc = mpiexec(["-m", "wrinkles", "run", str(scene), "--out", str(tmp_path / "out")],
                   n=2, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count(FREE_WARNING) == 1, proc.stderr


CONFLICTING_PINS = [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "tol": 1e-6},
                    {"point": [0.0, 0.0, 0.0], "normal": [1.0, 0.0, 0.0], "tol": 1e-6,
                     "velocity": [0.0, 0.0, 0.01]}]
"""A clamped bottom and a side pushed up: they share the nodes of the edge x = z = 0."""


@pytest.mark.parametrize("name", ["run", "check"])
def test_pins_moving_a_shared_node_differently_refused(tmp_path, capsys, name):
    """The run (on the body's nodes) and ``check`` (on the mesh's vertices): 3 shared nodes."""
    doc = set_key(base_scene(), "body.pins", CONFLICTING_PINS)
    scene = write_scene(tmp_path, doc)
    assert_refused(*run_cli(capsys, *command(name, scene, tmp_path / "out")),
                   "body.pins[0] and body.pins[1] both hold 3 node(s)", "component z",
                   "(0, 0, 0) m")
    assert not (tmp_path / "out").exists()


def test_check_reports_the_vertices_each_pin_holds(tmp_path, capsys):
    """The base cube (12 vertices on a face): the faces z = 0 and x = 0 held alike, and a
    pin of one vertex, warned about as the run warns; the counts are the run's (P1)."""
    pins = [CONFLICTING_PINS[0], {**CONFLICTING_PINS[1], "velocity": [0.0, 0.0, 0.0]},
            {"box": [[0.09, 0.09, 0.09], [0.11, 0.11, 0.11]]}]
    scene = write_scene(tmp_path, set_key(base_scene(), "body.pins", pins))
    with pytest.warns(UserWarning, match=re.escape("body.pins[2]: holds only 1 node(s)")):
        code = cli.main(["check", str(scene)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    resolved = json.loads(captured.out)["resolved"]
    assert resolved["mesh"]["pin_nodes"] == [12, 12, 1]
    with pytest.warns(UserWarning, match=re.escape("body.pins[2]: holds only 1 node(s)")):
        code = cli.main(["run", str(scene), "--out", str(tmp_path / "out")])
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["run"]["pin_nodes"] == [12, 12, 1]


# --------------------------------------------------------------------------------------------
# Two ranks: the same refusals end every rank (no deadlock)


@pytest.mark.mpi
@pytest.mark.parametrize("case", ["scene", "mesh", "resume", "pins", "empty_pin"])
def test_bad_input_on_two_ranks_exits_1_without_deadlock(tmp_path, mpiexec, case):
    doc = base_scene()
    extra: list[str] = []
    if case == "scene":
        set_key(doc, "material.nu", 0.5)
    elif case == "pins":  # found on the nodes of one rank or of both
        set_key(doc, "body.pins", CONFLICTING_PINS)
    elif case == "empty_pin":  # the span of every rank's nodes, gathered
        set_key(doc, "body.pins", [{"box": [[0.2, 0.0, 0.0], [0.3, 0.1, 0.1]]}])
    elif case == "mesh":
        points, cells = mesh_case("vertex_nonmanifold")
        meshio.write_points_cells(tmp_path / "body.vtu", points, cells)
        set_key(doc, "mesh", {"file": "body.vtu"})
    else:
        extra = ["--resume"]
    scene = write_scene(tmp_path, doc)
    proc = mpiexec(["-m", "wrinkles", "run", str(scene), "--out", str(tmp_path / "out"),
                    *extra], n=2, timeout=120)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert re.search({"scene": "nu", "mesh": "body.vtu", "resume": "checkpoint",
                      "pins": r"body\.pins\[0\] and body\.pins\[1\]",
                      "empty_pin": r"body\.pins\[0\]: the box from \(0\.2, 0, 0\) to "
                                   r"\(0\.3, 0\.1, 0\.1\) \(tol 1e-08 m\) selects no node "
                                   r"of the mesh, whose nodes span x 0 \.\. 0\.1, y 0 \.\. "
                                   r"0\.1, z 0 \.\. 0\.1 m$"}[case],
                     lines[0])


@pytest.mark.parametrize("name", ["run", "check"])
@pytest.mark.parametrize(("obstacle", "depth", "refused"), [
    ("body.contacts[0] (plane through [0.0, 0.0, 0.08]", "0.08", True),
    ("body.contacts[0] (plane through [0.0, 0.0, 0.01]", "0.01", False),
    ("rigid.balls[0] (sphere at [0.05, 0.05, 0.16] of radius 0.15", "0.08745", True),
    ("rigid.balls[0] (sphere at [0.05, 0.05, 0.2] of radius 0.12", "0.0184", False),
])
def test_a_body_starting_inside_an_obstacle(tmp_path, capsys, obstacle, depth, refused, name):
    """The base cube (z in [0, 0.1], mean cell 0.058 m) with a floor or a ball's sphere
    reaching ``depth`` into it at its nodes (the sphere's nearest node lies 0.0626 m from its
    centre): deeper than a mean cell is refused before anything is written; shallower is
    run with a warning naming the obstacle and the depth. ``wrinkles check`` says the same."""
    doc = set_key(base_scene(), "body.pins", ...)
    set_key(doc, "body.dynamics", "implicit_euler")
    set_key(doc, "body.dt", 1e-3)
    if obstacle.startswith("body"):
        floor = float(depth)
        set_key(doc, "body.contacts", [{"obstacle": "plane", "point": [0.0, 0.0, floor],
                                        "normal": [0.0, 0.0, 1.0]}])
    else:
        center, radius = ([0.05, 0.05, 0.16], 0.15) if refused else ([0.05, 0.05, 0.2], 0.12)
        set_key(doc, "rigid.balls", [{"radius": radius, "mass": 1.0, "center": center,
                                      "velocity": [0.0, 0.0, 0.0]}])
    scene = write_scene(tmp_path, doc)
    out = tmp_path / "out"
    if refused:
        assert_refused(*run_cli(capsys, *command(name, scene, out)),
                       obstacle, f"{depth} m inside it")
        assert not out.exists()
        return
    with pytest.warns(UserWarning, match=re.escape(obstacle) + f".*start inside it, up to {depth}"):
        code, err = run_cli(capsys, *command(name, scene, out))
    assert code == 0, err


@pytest.mark.parametrize("name", ["run", "check"])
def test_a_body_resting_on_the_floor_within_round_off_starts_clear(tmp_path, capsys, name):
    """A floor 1e-17 m above the cube's bottom z = 0 (the round-off of a mesh file's
    coordinates): touching, no warning."""
    doc = set_key(base_scene(), "body.pins", ...)
    set_key(doc, "body.dynamics", "implicit_euler")
    set_key(doc, "body.dt", 1e-3)
    set_key(doc, "body.contacts", [{"obstacle": "plane", "point": [0.0, 0.0, 1e-17],
                                    "normal": [0.0, 0.0, 1.0]}])
    scene = write_scene(tmp_path, doc)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, err = run_cli(capsys, *command(name, scene, tmp_path / "out"))
    assert code == 0, err
    assert not [w for w in caught if "inside it" in str(w.message)]


@pytest.mark.parametrize("name", ["run", "check"])
def test_a_ball_centred_inside_the_body_refused(tmp_path, capsys, name):
    doc = set_key(base_scene(), "body.pins", ...)
    set_key(doc, "body.dynamics", "implicit_euler")
    set_key(doc, "rigid.balls", [{"radius": 0.01, "mass": 1.0, "center": [0.05, 0.04, 0.03]}])
    scene = write_scene(tmp_path, doc)
    assert_refused(*run_cli(capsys, *command(name, scene, tmp_path / "out")),
                   "rigid.balls[0].center = [0.05, 0.04, 0.03]: inside the body")
