"""Fuzzing: mutated scene files through ``wrinkles check`` and mutated meshes through validate.

Scene files start from the real schema (a valid scene resolved by ``scene_dict``: every
table and key the loader knows) and get 1-3 mutations: delete a key, replace a value by a
random one (NaN, inf, huge, negative, wrong type, nested tables), add an unknown key. Each
file goes through ``wrinkles.cli.main(["check", file])`` in process: the exit code must be
0 or 1 (2 would be an unexpected exception, i.e. a bug) and a refusal one ``error:`` line.
Meshes start from a valid cube and get mutated arrays; ``meshes.validate`` may only raise
``InputError``. Example counts are bounded (derandomized) so the file runs in well under 60 s.
"""

from __future__ import annotations

import contextlib
import io
import json
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import base_scene, cube_tets, dumps

import wrinkles.cli as cli
from meshes.errors import InputError
from meshes.validate import validate
from wrinkles.scene import scene_dict, scene_from_dict

FUZZ = settings(max_examples=250, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])


def schema_scene() -> dict[str, Any]:
    """A valid scene with every key the loader knows (``None`` values dropped: no TOML null)."""
    doc = base_scene()
    doc["body"]["contacts"] = [{"obstacle": "sphere", "point": [0.05, 0.05, 0.2],
                                "radius": 0.05}]
    full = json.loads(json.dumps(scene_dict(scene_from_dict(doc, Path.cwd()))))
    return prune(full)


def prune(value: Any) -> Any:
    """Drop ``None`` entries recursively."""
    if isinstance(value, dict):
        return {k: prune(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [prune(v) for v in value if v is not None]
    return value


def paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path (dict keys and list indices) of a nested document."""
    items = (doc.items() if isinstance(doc, dict) else
             enumerate(doc) if isinstance(doc, list) else [])
    found: list[tuple[Any, ...]] = []
    for k, v in items:
        found.append((*prefix, k))
        found += paths(v, (*prefix, k))
    return found


SCALARS = st.one_of(
    st.booleans(), st.integers(-10**20, 10**20),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1e300, -1e-300, 0.5, 0.499999, 1e-12, 3]),
    st.text(max_size=6), st.sampled_from(["box", "plane", "sphere", "static", "newmark", ""]))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=4),
    st.dictionaries(st.sampled_from(["kind", "E", "x", "frames", "point"]), inner, max_size=3)),
    max_leaves=6)
MUTATION = st.tuples(st.sampled_from(["delete", "replace", "add"]), st.integers(0, 10**6),
                     VALUES, st.text(alphabet="abcxyz_", min_size=1, max_size=5))


def mutate(doc: dict[str, Any], op: str, pick: int, value: Any, name: str) -> None:
    """Apply one mutation at the ``pick``-th key path (modulo their number)."""
    all_paths = paths(doc)
    *parent_path, last = all_paths[pick % len(all_paths)]
    parent: Any = doc
    for k in parent_path:
        parent = parent[k]
    if op == "delete":
        del parent[last]
    elif op == "replace":
        parent[last] = value
    elif isinstance(parent, dict):
        parent[f"{name}_unknown"] = value
    else:
        parent.append(value)


def check_in_process(path: Path) -> tuple[int, str]:
    """``wrinkles check PATH`` in process; return the exit code and stderr."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err), \
            warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = cli.main(["check", str(path)])
    return code, err.getvalue()


SCHEMA = schema_scene()
WORKDIR = Path(tempfile.mkdtemp(prefix="fuzz_scene_"))
OUTCOMES: dict[int, int] = {}


@FUZZ
@given(st.lists(MUTATION, min_size=1, max_size=3))
def test_mutated_scene_files_give_exit_0_or_a_one_line_refusal(mutations):
    doc = json.loads(json.dumps(SCHEMA))
    for mutation in mutations:
        mutate(doc, *mutation)
    path = WORKDIR / "scene.toml"
    path.write_text(dumps(doc))
    code, err = check_in_process(path)
    OUTCOMES[code] = OUTCOMES.get(code, 0) + 1
    assert code in (0, 1), err
    if code == 1:
        assert err.count("\n") == 1 and err.startswith("error: "), err
        assert "Traceback" not in err


def test_fuzz_reached_both_outcomes():
    """The mutations are neither all harmless nor all fatal (run after the fuzz test)."""
    if not OUTCOMES:  # run alone (-k): fuzz first
        test_mutated_scene_files_give_exit_0_or_a_one_line_refusal()
    print(f"scene fuzz outcomes (exit code: count): {OUTCOMES}")
    assert OUTCOMES.get(1, 0) > 20 and OUTCOMES.get(0, 0) > 5


SHAPE_BREAKING = ("float_tets", "drop_column", "empty", "transpose")
"""Mutations after which the arrays are no longer (n, 3) floats / (m, 4) ints: applied last."""
MESH_OPS = st.tuples(
    st.sampled_from(["scale", "nan", "collapse", "swap", "duplicate", "index", "negative",
                     "float_tets", "drop_column", "shift_point", "empty", "transpose"]),
    st.integers(0, 10**6),
    st.one_of(st.floats(-1e15, 1e15), st.sampled_from([np.nan, np.inf, 0.0, 1e-300])))


def mutate_mesh(points: np.ndarray, tets: np.ndarray, op: str, pick: int,
                value: float) -> tuple[Any, Any]:
    """Return mutated copies of ``points`` and ``tets`` (possibly of another type/shape)."""
    p, t = points.copy(), tets.copy()
    i, j = pick % len(p), pick % len(t)
    if op in SHAPE_BREAKING:
        return {"float_tets": (p, t.astype(float) + value), "drop_column": (p, t[:, :3]),
                "empty": (p[:0], t[:0]), "transpose": (p.T, t)}[op]
    if op == "scale":
        p = p * value
    elif op in ("nan", "collapse", "shift_point"):
        p[i] = {"nan": np.where(np.arange(3) == pick % 3, np.nan, p[i]),
                "collapse": p[(i + 1) % len(p)], "shift_point": p[i] + value}[op]
    elif op == "duplicate":
        t = np.vstack([t, t[j:j + 1]])
    else:
        k = pick % 4
        t[j, k] = {"swap": t[j, (k + 1) % 4], "index": pick, "negative": -1 - pick % 5}[op]
    return p, t


@FUZZ
@given(st.lists(MESH_OPS, min_size=1, max_size=3))
def test_mutated_mesh_arrays_raise_only_input_error(ops):
    points, tets = cube_tets()
    for op in ops:
        points, tets = mutate_mesh(points, tets, *op)
        if op[0] in SHAPE_BREAKING:
            break
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            mesh = validate(points, tets, source="fuzz.vtu")
        except InputError as exc:
            assert "fuzz.vtu" in str(exc) and "\n" not in str(exc)
            return
    assert np.all(np.isfinite(mesh.points)) and len(mesh.tets) > 0
