"""Quality presets (``quality = "preview" | "balanced" | "final"``): overlay and precedence."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from support import REPO

from meshes.errors import InputError
from wrinkles.presets import PRESET_ROWS, PRESETS, apply_quality, preset_keys
from wrinkles.scene import Scene, load_scene, scene_dict
from wrinkles.shell_setup import SolverKeys

DEFAULT = REPO / "scenes" / "default.toml"

BODY_ONLY = """
[mesh]
builder = "box"
params = { lx = 0.2, ly = 0.05, lz = 0.05, h = 0.05 }
"""


def lookup(doc: Any, key: str) -> Any:
    """Value of a dotted key in a nested dict (a table may spell the rest as one dotted key)."""
    parts = key.split(".")
    for k in range(len(parts), 0, -1):
        head = ".".join(parts[:k])
        if isinstance(doc, dict) and head in doc:
            return doc[head] if k == len(parts) else lookup(doc[head], ".".join(parts[k:]))
    raise KeyError(key)


def explicit_default() -> str:
    """``scenes/default.toml`` without its ``quality`` line, the balanced keys written out."""
    text = "\n".join(line for line in DEFAULT.read_text().splitlines()
                     if not line.startswith("quality")) + "\n"
    for table, keys in (("[body]", "degree = 1"), ("[shell.subdivision]", "levels = 2"),
                        ("[shell.coupling]", None)):
        assert table in text, table
        if keys is not None:
            text = text.replace(f"{table}\n", f"{table}\n{keys}\n", 1)
    return text.replace("[shell.coupling]", "[shell.solver]\nrtol = 1e-4\nmax_iterations = 300"
                        "\n\n[shell.coupling]", 1)


def scene_with(tmp_path: Path, header: str, body: str | None = None) -> Path:
    """The explicit default scene (or ``body``) with ``header`` lines prepended at the top."""
    path = tmp_path / "scene.toml"
    path.write_text(header + "\n" + (body if body is not None else explicit_default()))
    return path


def levels_of(scene: Scene) -> int:
    """Subdivision levels of a scene with a shell."""
    assert scene.shell is not None
    return scene.shell.subdivision.levels


def without(text: str, *prefixes: str) -> str:
    """Scene text without the lines starting with ``prefixes`` (to let the preset decide)."""
    return "\n".join(line for line in text.splitlines()
                     if not line.lstrip().startswith(prefixes))


@pytest.mark.parametrize("quality", sorted(PRESETS))
def test_preset_resolves_to_its_documented_keys(tmp_path, quality):
    body = without(explicit_default(), "levels", "rtol = 1e-4", "max_iterations", "degree")
    resolved = scene_dict(load_scene(scene_with(tmp_path, f'quality = "{quality}"', body)))
    for key, value in PRESETS[quality].items():
        assert lookup(resolved, key) == value, key


def test_presets_differ_and_order_by_resolution():
    levels = [PRESETS[q]["shell.subdivision.levels"] for q in ("preview", "balanced", "final")]
    rtols = [PRESETS[q]["shell.solver.rtol"] for q in ("preview", "balanced", "final")]
    assert levels == sorted(levels) and len(set(levels)) == 3
    assert rtols == sorted(rtols, reverse=True)


def test_explicit_scene_keys_win_over_the_preset(tmp_path):
    # the explicit default writes levels = 2, rtol = 1e-4 and body degree = 1
    scene = load_scene(scene_with(tmp_path, 'quality = "final"'))
    assert scene.shell is not None
    assert scene.shell.subdivision.levels == 2 and scene.body.degree == 1
    assert scene.shell.solver.rtol == 1e-4
    # a key the file leaves out comes from the preset (the dataclass default is another)
    body = without(explicit_default(), "max_iterations")
    shell = load_scene(scene_with(tmp_path, 'quality = "final"', body)).shell
    assert shell is not None and shell.subdivision.levels == 2
    assert shell.solver.max_iterations == PRESETS["final"]["shell.solver.max_iterations"]
    assert shell.solver.max_iterations != SolverKeys().max_iterations


def test_set_wins_over_file_and_preset_and_selects_the_preset(tmp_path):
    body = without(explicit_default(), "levels")
    path = scene_with(tmp_path, 'quality = "final"', body)
    assert levels_of(load_scene(path)) == PRESETS["final"]["shell.subdivision.levels"]
    scene = load_scene(path, ["shell.subdivision.levels=0", "shell.solver.rtol=0.5"])
    assert scene.shell is not None
    assert scene.shell.subdivision.levels == 0 and scene.shell.solver.rtol == 0.5
    plain = scene_with(tmp_path, "", body)
    assert levels_of(load_scene(plain, ["quality=preview"])) == PRESETS["preview"][
        "shell.subdivision.levels"]


def test_no_quality_leaves_the_scene_unchanged(tmp_path):
    assert scene_dict(load_scene(scene_with(tmp_path, ""))) == scene_dict(load_scene(DEFAULT))


def test_preset_never_switches_physics_on(tmp_path):
    scene = load_scene(scene_with(tmp_path, 'quality = "final"', BODY_ONLY))
    assert scene.shell is None


@pytest.mark.parametrize("bad", ['"fast"', "3", '"Final"'])
def test_unknown_quality_is_an_input_error_naming_the_key(tmp_path, bad):
    with pytest.raises(InputError) as info:
        load_scene(scene_with(tmp_path, f"quality = {bad}"))
    message = str(info.value)
    assert message.startswith("scene.toml: quality:") and "'balanced'" in message


def test_apply_quality_reports_the_keys_it_set():
    doc: dict[str, Any] = {"shell": {"solver": {"rtol": 1e-2}}, "quality": "balanced"}
    applied = apply_quality(doc)
    assert "quality" not in doc
    assert "shell.solver.rtol" not in applied and doc["shell"]["solver"]["rtol"] == 1e-2
    assert set(applied) == set(preset_keys("balanced")) - {"shell.solver.rtol"}
    assert doc["shell"]["subdivision"]["levels"] == PRESETS["balanced"][
        "shell.subdivision.levels"]


def test_default_scene_is_the_balanced_preset(tmp_path):
    """scenes/default.toml selects ``balanced``: it resolves exactly like the keys written out."""
    assert 'quality = "balanced"' in DEFAULT.read_text()
    explicit = scene_with(tmp_path, "")
    assert scene_dict(load_scene(DEFAULT)) == scene_dict(load_scene(explicit))


def test_every_preset_names_the_sweep_row_that_measured_it():
    """PRESET_ROWS maps each quality to a row name of benchmarks/speed_accuracy.py's sweep."""
    from benchmarks.speed_accuracy import SceneFacts, sweep

    facts = SceneFacts(levels=2, hessian="exact", far_hessian="", rtol=1e-4, h=0.02,
                       dynamic=False, dt=0.25, steps_per_frame=1, frames=4)
    names = {c.name for c in sweep([0, 1, 2, 3], facts, None)} | {"reference"}
    assert set(PRESET_ROWS) == set(PRESETS)
    assert set(PRESET_ROWS.values()) <= names, set(PRESET_ROWS.values()) - names
    assert PRESET_ROWS["balanced"] == "base"  # scenes/default.toml is the balanced preset
