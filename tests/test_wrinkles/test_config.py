"""Scene files: the generic TOML -> dataclass loader and the scene tables (no solve)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest
from support import EXTERNAL_MESHES, REPO

from meshes.errors import InputError
from solvers.shell_newton import ShellNewtonOptions
from wrinkles.config import Source, apply_override, build, expert, parse_literal, to_dict
from wrinkles.output import OutputOptions, json_text
from wrinkles.scene import Scene, load_scene, scene_dict, scene_from_dict, with_frames

DEFAULT = REPO / "scenes" / "drop_block.toml"  # the falling block (default.toml: wrinkles)

BASE = """
[mesh]
builder = "box"
params = { lx = 0.4, ly = 0.4, lz = 0.2, h = 0.1 }

[material]
E = 5.0e4
nu = 0.35

[body]
dynamics = "implicit_euler"
dt = 0.01

[[body.contacts]]
obstacle = "plane"
"""


def write_scene(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def load_error(tmp_path: Path, text: str, overrides: list[str] | None = None) -> str:
    with pytest.raises(InputError) as info:
        load_scene(write_scene(tmp_path, text), overrides)
    message = str(info.value)
    assert "\n" not in message
    return message


# --- the default scene ------------------------------------------------------------------------


def test_default_scene_loads_with_its_values():
    scene = load_scene(DEFAULT)
    assert scene.mesh.builder == "box"
    assert scene.mesh.params["origin"] == (0.0, 0.0, 0.02)  # Sequence[float] -> tuple
    assert scene.material.E == 5.0e4 and scene.material.nu == 0.35
    assert scene.body.dynamics == "implicit_euler" and scene.body.dt == 0.01
    assert len(scene.body.contacts) == 1 and scene.body.contacts[0].obstacle == "plane"
    assert scene.time.frames == 30
    assert scene.body.pins == ()


def test_absent_tables_mean_physics_off(tmp_path):
    scene = load_scene(write_scene(tmp_path, '[mesh]\nbuilder = "sphere"\n'
                                   'params = { radius = 0.1, h = 0.05 }\n'))
    assert scene.body.contacts == () and scene.body.pins == ()
    assert scene.body.dynamics == "static"
    assert scene.time.frames == 1


@pytest.mark.parametrize("path", sorted((REPO / "scenes").glob("*.toml")), ids=lambda p: p.name)
def test_every_scene_loads_and_explains_itself(path):
    if "meshes_external" in path.read_text() and not EXTERNAL_MESHES.is_dir():
        pytest.skip("the scene uses ../shared/meshes_external, not beside this checkout")
    scene = load_scene(path)
    assert scene.title
    assert path.read_text().startswith("# ")  # a comment at the top says what it shows
    assert scene.time.frames >= 1


@pytest.mark.parametrize(("every", "written"), [(1, [1, 2, 3, 4, 5, 6, 7]), (3, [3, 6, 7])])
def test_output_every_n_frames_and_the_last(every, written):
    options = OutputOptions(every=every)
    assert [k for k in range(1, 8) if options.writes_frame(k, 7)] == written
    assert not any(OutputOptions(xdmf=False).writes_frame(k, 7) for k in range(1, 8))


# --- errors name the file and the dotted key ---------------------------------------------------


def test_unknown_top_level_table_suggests(tmp_path):
    message = load_error(tmp_path, BASE + "\n[materal]\nE = 1.0\n")
    assert message == "scene.toml: unknown key 'materal' (did you mean 'material'?)"


def test_misspelled_nested_key_suggests(tmp_path):
    message = load_error(tmp_path, BASE.replace("dt = 0.01", "dt = 0.01\ngravty = [0, 0, -1]"))
    assert message == "scene.toml: unknown key 'body.gravty' (did you mean 'gravity'?)"


def test_misspelled_key_in_array_of_tables(tmp_path):
    message = load_error(tmp_path, BASE + "normall = [0, 0, 1]\n")
    assert message == "scene.toml: unknown key 'body.contacts[0].normall' (did you mean 'normal'?)"


def test_unknown_key_without_close_match(tmp_path):
    message = load_error(tmp_path, BASE.replace("E = 5.0e4", "E = 5.0e4\nzzzz = 1"))
    assert message == "scene.toml: unknown key 'material.zzzz'"


def test_unknown_builder_parameter_checked_against_signature(tmp_path):
    message = load_error(tmp_path, BASE.replace("h = 0.1", "hh = 0.1"))
    assert message == "scene.toml: unknown key 'mesh.params.hh' (did you mean 'h'?)"


def test_missing_builder_parameter(tmp_path):
    message = load_error(tmp_path, BASE.replace("lz = 0.2, ", ""))
    assert message == "scene.toml: missing key 'mesh.params.lz'"


@pytest.mark.parametrize(("old", "new", "expected"), [
    ("E = 5.0e4", 'E = "soft"', "scene.toml: material.E: expected float, got str 'soft'"),
    ("E = 5.0e4", "E = true", "scene.toml: material.E: expected float, got bool True"),
    ('dynamics = "implicit_euler"', "dynamics = 1",
     "scene.toml: body.dynamics: expected str, got int 1"),
    ("h = 0.1", 'h = "x"', "scene.toml: mesh.params.h: expected float, got str 'x'"),
    ("dt = 0.01", "dt = 0.01\ngravity = [0.0, -9.81]",
     "scene.toml: body.gravity: expected 3 values, got 2"),
    ("dt = 0.01", "dt = 0.01\ngravity = 9.81",
     "scene.toml: body.gravity: expected an array (tuple[float, float, float]), got 9.81"),
    ('[material]', '[material]\nmodel = ["stvk"]',
     "scene.toml: material.model: expected str, got list ['stvk']"),
])
def test_wrong_type_names_key(tmp_path, old, new, expected):
    assert old in BASE
    assert load_error(tmp_path, BASE.replace(old, new)) == expected


def test_negative_young_modulus(tmp_path):
    message = load_error(tmp_path, BASE.replace("E = 5.0e4", "E = -1.0"))
    assert message == "scene.toml: material.E must be > 0, got -1.0"


def test_incompressible_poisson_ratio_refused(tmp_path):
    message = load_error(tmp_path, BASE.replace("nu = 0.35", "nu = 0.5"))
    assert message.startswith("scene.toml: material.nu must be < 0.5")


@pytest.mark.parametrize("value", ["nan", "-nan", "+nan"])
def test_nan_value_refused(tmp_path, value):
    message = load_error(tmp_path, BASE.replace("E = 5.0e4", f"E = {value}"))
    assert message == "scene.toml: material.E: must be a number, got nan"


def test_infinite_modulus_refused_by_material(tmp_path):
    message = load_error(tmp_path, BASE.replace("E = 5.0e4", "E = inf"))
    assert message == "scene.toml: material.E must be finite, got inf"


def test_missing_mesh_file(tmp_path):
    text = BASE.replace('builder = "box"\nparams = { lx = 0.4, ly = 0.4, lz = 0.2, h = 0.1 }',
                        'file = "nowhere/body.msh"')
    message = load_error(tmp_path, text)
    assert message == f"scene.toml: mesh.file: no such mesh file '{tmp_path}/nowhere/body.msh'"


def test_mesh_needs_builder_or_file(tmp_path):
    message = load_error(tmp_path, BASE.replace('builder = "box"',
                                                'builder = "box"\nfile = "a.msh"'))
    assert message == ("scene.toml: mesh: give exactly one of 'mesh.builder' or 'mesh.file'")


def test_mesh_file_relative_to_scene_directory(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "body.vtu").write_text("not read at load time")
    text = BASE.replace('builder = "box"\nparams = { lx = 0.4, ly = 0.4, lz = 0.2, h = 0.1 }',
                        'file = "meshes/body.vtu"')
    scene = load_scene(write_scene(tmp_path, text))
    assert scene.mesh.file == str((tmp_path / "meshes" / "body.vtu").resolve())


def test_unknown_builder_suggests(tmp_path):
    message = load_error(tmp_path, BASE.replace('builder = "box"', 'builder = "boxx"'))
    assert message.startswith("scene.toml: mesh.builder must be one of ('box', ")


@pytest.mark.parametrize(("text", "message"), [
    ("\n[time]\nend_time = 0.1\n", "time.end_time: no longer a scene key; give time.frames"),
    ("\n[newton]\natol = 1e-8\n", "newton.atol: no longer a scene key; set it in "
                                  "[newton.options]"),
    ("\n[[body.pins]]\nkind = \"box\"\n", "body.pins[0].kind: no longer a scene key; a pin "
                                         "with 'box' selects a box"),
    ("\n[[body.pins]]\npoint = [0, 0, 0]\n[[body.pins]]\nbox_min = [0, 0, 0]\n",
     "body.pins[1].box_min: no longer a scene key; give box = [[xmin, ymin, zmin], "),
    ("\n[[body.contacts]]\nobstacle = \"sphere\"\ncenter = [0, 0, 1]\n",
     "body.contacts[1].center: no longer a scene key; a sphere's centre is its 'point'"),
    ("\n[rigid.coupling]\nrtol = 1e-6\n", "rigid.coupling: no longer a scene key; set rtol / "
                                          "max_iterations in [rigid.options]"),
    ("\n[output]\ncheckpoint = false\n", "output.checkpoint: no longer a scene key; "
                                         "checkpoint.h5 is always written"),
])
def test_retired_key_names_its_replacement(tmp_path, text, message):
    assert load_error(tmp_path, BASE + text).startswith(f"scene.toml: {message}")


def test_expert_mappings_reach_the_solvers(tmp_path):
    """newton.options and rigid.options set the internal options; named keys stay apart."""
    text = BASE + "\n[[rigid.balls]]\nmass = 2.0\ncenter = [0.2, 0.2, 0.5]\n"
    scene = load_scene(write_scene(tmp_path, text),
                       ["rigid.options.rtol=1e-7", "newton.options.max_it=7"])
    assert scene.rigid is not None and scene.rigid.internals.coupling.rtol == 1e-7
    assert scene.rigid.internals.coupling.max_iterations == 30
    assert scene.rigid.internals.balls[0].mass == 2.0
    assert scene.newton.internals.max_it == 7 and scene.newton.internals.rtol == 1e-9
    assert "did you mean 'rtol'" in load_error(tmp_path, text, ["rigid.options.rtl=1"])
    assert load_error(tmp_path, text, ["newton.options.rtol=1e-3"]).endswith(
        "newton.options.rtol: set by a named key of the scene, not here")


def test_time_reads_frames_and_defaults_to_one_frame(tmp_path):
    scene = load_scene(write_scene(tmp_path, BASE + "\n[time]\nframes = 5\n"
                                   "steps_per_frame = 2\n"))
    assert (scene.time.frames, scene.time.steps_per_frame) == (5, 2)
    default = load_scene(write_scene(tmp_path, BASE, "plain.toml")).time
    assert (default.frames, default.steps_per_frame) == (1, 1)


def test_invalid_toml_names_file(tmp_path):
    message = load_error(tmp_path, BASE + "\n[material\n")
    assert message.startswith("scene.toml: invalid TOML: ")


def test_missing_scene_file(tmp_path):
    with pytest.raises(InputError, match=r"nope\.toml: scene file not found$"):
        load_scene(tmp_path / "nope.toml")


def test_required_mesh_table(tmp_path):
    assert load_error(tmp_path, "[material]\nE = 1.0\n") == "scene.toml: missing key 'mesh'"


# --- --set overrides -------------------------------------------------------------------------


def test_overrides_change_values_and_turn_physics_on(tmp_path):
    path = write_scene(tmp_path, BASE)
    scene = load_scene(path, ["material.E=2e4", "body.gravity=[0, 0, -1.62]",
                              "time.frames=7", "mesh.params.h=0.2", "output.xdmf=false",
                              'title="moon"'])
    assert scene.material.E == 2.0e4 and isinstance(scene.material.E, float)
    assert scene.body.gravity == (0.0, 0.0, -1.62)
    assert scene.time.frames == 7 and scene.mesh.params["h"] == 0.2
    assert scene.output.xdmf is False and scene.title == "moon"
    assert load_scene(path).material.E == 5.0e4  # the file is untouched


def test_override_bare_word_is_a_string(tmp_path):
    scene = load_scene(write_scene(tmp_path, BASE), ["material.model=stvk"])
    assert scene.material.model == "stvk"


def test_override_errors_name_the_override(tmp_path):
    path = write_scene(tmp_path, BASE)
    with pytest.raises(InputError) as info:
        load_scene(path, ["material.E=soft"])
    assert str(info.value) == "scene.toml: --set material.E: expected float, got str 'soft'"
    with pytest.raises(InputError, match=r"unknown key 'material.EE' \(did you mean 'E'\?\)"):
        load_scene(path, ["material.EE=1"])
    with pytest.raises(InputError, match="--set expects key=value"):
        load_scene(path, ["material.E"])
    with pytest.raises(InputError, match=r"--set material.E.x: 'material.E' is not a table"):
        load_scene(path, ["material.E.x=1"])


def test_parse_literal():
    assert parse_literal("1e4") == 1.0e4
    assert parse_literal("3") == 3 and isinstance(parse_literal("3"), int)
    assert parse_literal("[1, 2.5]") == [1, 2.5]
    assert parse_literal("true") is True
    assert parse_literal('"a b"') == "a b"
    assert parse_literal("box") == "box"
    assert math.isnan(parse_literal("nan"))


def test_apply_override_creates_tables():
    doc: dict = {}
    assert apply_override(doc, "a.b.c = 2", "x.toml") == "a.b.c"
    assert doc == {"a": {"b": {"c": 2}}}


def test_with_frames_replaces_the_frame_count(tmp_path):
    scene = load_scene(write_scene(tmp_path, BASE + "\n[time]\nframes = 7\n"))
    assert with_frames(scene, 4).time.frames == 4
    with pytest.raises(InputError, match=r"^--frames: time.frames must be >= 1, got 0$"):
        with_frames(scene, 0)


# --- round trip of the resolved configuration --------------------------------------------------


def test_resolved_scene_round_trips_through_json(tmp_path):
    text = BASE + """
[[body.pins]]
box = [[-inf, -inf, -1.0], [inf, inf, 0.0]]
components = [2]

[[body.contacts]]
obstacle = "sphere"
point = [0.2, 0.2, 0.5]
radius = 0.1

[time]
frames = 3
"""
    scene = load_scene(write_scene(tmp_path, text), ["body.contact_stiffness=1e6"])
    data = json.loads(json_text(scene_dict(scene)))  # strict JSON, as summary.json has it
    assert data["body"]["pins"][0]["box"] == [["-inf", "-inf", -1.0], ["inf", "inf", 0.0]]
    again = scene_from_dict(data, tmp_path, "summary.json")
    assert again == scene
    assert again.body.pins[0].box == ((-math.inf, -math.inf, -1.0), (math.inf, math.inf, 0.0))
    assert data["body"]["contact_stiffness"] == 1.0e6
    assert data["body"]["contacts"][1]["point"] == [0.2, 0.2, 0.5]
    assert data["mesh"]["params"] == {"lx": 0.4, "ly": 0.4, "lz": 0.2, "h": 0.1}
    assert set(data) == {"mesh", "title", "up", "material", "body", "newton", "time", "output",
                         "shell"}


def test_default_scene_round_trips(tmp_path):
    scene = load_scene(DEFAULT)
    assert scene_from_dict(json.loads(json.dumps(scene_dict(scene))), tmp_path) == scene
    assert isinstance(scene_from_dict(scene_dict(scene), tmp_path), Scene)


# --- the generic loader on its own dataclasses ---------------------------------------------------


@dataclass(frozen=True)
class Leaf:
    """Test leaf.

    Attributes:
        kind: a Literal choice.
        weights: a variable-length tuple.

    """

    kind: Literal["a", "bb"] = "a"
    weights: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if any(w < 0 for w in self.weights):
            raise InputError("leaf.weights must be >= 0")


@dataclass(frozen=True)
class Root:
    """Test root.

    Attributes:
        count: an int.
        leaf: an optional nested table.
        leaves: a list of tables.
        labels: a free table of strings.

    """

    count: int = 1
    leaf: Leaf | None = None
    leaves: list[Leaf] = field(default_factory=list)
    labels: dict[str, str] = field(default_factory=dict)


def test_generic_build_of_nested_types():
    src = Source("t.toml")
    root = build(Root, {"count": 2, "leaf": {"kind": "bb", "weights": [1, 2.5]},
                        "leaves": [{}, {"kind": "bb"}], "labels": {"x": "y"}}, "", src)
    assert root == Root(2, Leaf("bb", (1.0, 2.5)), [Leaf(), Leaf("bb")], {"x": "y"})
    assert isinstance(root.leaf.weights[0], float)
    assert build(Root, to_dict(root), "", src) == root
    assert build(Root, {}, "", src).leaf is None  # absent table: off


@dataclass(frozen=True)
class Tuned:
    """Test parent whose nested default differs from the nested class's own defaults.

    Attributes:
        leaf: defaults to ``Leaf("bb", (2.0,))``, not ``Leaf()``.
        count: an int.

    """

    leaf: Leaf = field(default_factory=lambda: Leaf("bb", (2.0,)))
    count: int = 0


def test_a_partial_nested_table_keeps_the_rest_of_the_field_default():
    """A sub-table names only what it changes: the other values are the field default's."""
    src = Source("t.toml")
    assert build(Tuned, {"leaf": {"weights": [3]}}, "", src) == Tuned(Leaf("bb", (3.0,)))
    assert build(Tuned, {"count": 1}, "", src) == Tuned(Leaf("bb", (2.0,)), 1)
    with pytest.raises(InputError, match=r"unknown key 'leaf.kinds' \(did you mean 'kind'"):
        build(Tuned, {"leaf": {"kinds": "a"}}, "", src)


def test_an_expert_key_inside_a_tuned_solver_table_keeps_its_other_defaults():
    """``shell.solver.options`` ``newton.augmented_linear.mumps_blr_tolerance`` alone: the
    augmented system keeps its LDL^T (a bare ``LinearSolverOptions`` would be Cholesky, which
    the shell Newton refuses for an indefinite system)."""
    options = expert(ShellNewtonOptions, {"augmented_linear.mumps_blr_tolerance": 1e-6},
                     "shell.solver.options.newton")
    assert options.augmented_linear.symmetric == "ldlt"
    assert options.augmented_linear.mumps_blr_tolerance == 1e-6
    assert options.linear.symmetric == "cholesky"


@pytest.mark.parametrize(("table", "expected"), [
    ({"count": 1.5}, "t.toml: count: expected int, got float 1.5"),
    ({"count": True}, "t.toml: count: expected int, got bool True"),
    ({"leaf": {"kind": "b"}}, "t.toml: leaf.kind: must be one of 'a', 'bb', got 'b' "
                              "(did you mean 'bb'?)"),
    ({"leaf": 3}, "t.toml: leaf: expected a table, got 3"),
    ({"leaves": [{}, {"weights": [1, "x"]}]},
     "t.toml: leaves[1].weights[1]: expected float, got str 'x'"),
    ({"leaves": [{"weights": [-1.0]}]}, "t.toml: leaves[0]: leaf.weights must be >= 0"),
    ({"leaf": {"weights": [-1.0]}}, "t.toml: leaf.weights must be >= 0"),
    ({"leaf": {"wieghts": []}}, "t.toml: unknown key 'leaf.wieghts' (did you mean 'weights'?)"),
    ({"labels": {"x": 1}}, "t.toml: labels.x: expected str, got int 1"),
])
def test_generic_build_errors(table, expected):
    with pytest.raises(InputError) as info:
        build(Root, table, "", Source("t.toml"))
    assert str(info.value) == expected


def test_override_with_inline_table_turns_contact_on(tmp_path):
    text = BASE.replace('[[body.contacts]]\nobstacle = "plane"\n', "")
    scene = load_scene(write_scene(tmp_path, text),
                       ['body.contacts=[{obstacle = "sphere", radius = 0.5}]'])
    assert [(c.obstacle, c.radius) for c in scene.body.contacts] == [("sphere", 0.5)]
    assert load_scene(write_scene(tmp_path, text)).body.contacts == ()


@pytest.mark.parametrize(("params", "expected"), [
    ('{ radius = 0.1, length = 0.5, h = 0.05, axis = "x" }', {"axis": "x"}),
    ("{ radius = 0.1, length = 0.5, h = 0.05, axis = [1, 0, 1] }", {"axis": (1.0, 0.0, 1.0)}),
])
def test_builder_params_follow_the_builder_annotations(tmp_path, params, expected):
    text = f'[mesh]\nbuilder = "cylinder"\nparams = {params}\n'
    scene = load_scene(write_scene(tmp_path, text))
    assert {k: scene.mesh.params[k] for k in expected} == expected


def test_builder_params_nested_dataclass(tmp_path):
    from meshes.builders import SofaDimensions

    text = '[mesh]\nbuilder = "sofa"\nparams = { width = 2.0, h = 0.2, dims = { depth = 0.8 } }\n'
    scene = load_scene(write_scene(tmp_path, text))
    assert scene.mesh.params["dims"] == SofaDimensions(depth=0.8)
    message = load_error(tmp_path, text.replace("depth = 0.8", "depht = 0.8"))
    assert message == "scene.toml: unknown key 'mesh.params.dims.depht' (did you mean 'depth'?)"
    message = load_error(tmp_path, text.replace("h = 0.2", "h = 0.2, cache = false"))
    assert message == "scene.toml: unknown key 'mesh.params.cache'"  # not the scene's business
    assert scene_from_dict(json.loads(json.dumps(scene_dict(scene))), tmp_path) == scene


@pytest.mark.parametrize(("extra", "expected"), [
    ("\n[output]\nevery = 0\n", "scene.toml: output.every must be >= 1, got 0"),
    ("\n[time]\nframes = 0\n", "scene.toml: time.frames must be >= 1, got 0"),
    ("\n[time]\nsteps_per_frame = 0\n", "scene.toml: time.steps_per_frame must be >= 1, got 0"),
    ("\n[newton.options]\nmax_it = 0\n", "scene.toml: newton.options: newton.max_it must be >= 1, "
                                          "got 0"),
    ("\n[output]\nxdmf = 1\n", "scene.toml: output.xdmf: expected bool, got int 1"),
])
def test_value_checks_of_the_other_tables(tmp_path, extra, expected):
    assert load_error(tmp_path, BASE + extra) == expected
