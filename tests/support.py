"""Helpers shared by the test modules: the CLI in a subprocess, XDMF readers, scene texts."""

from __future__ import annotations

import importlib.util
import json
import math
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from types import ModuleType
from typing import Any

import h5py
import meshio
import numpy as np
import pytest
from scipy.spatial import cKDTree

from validation.scene_runs import wrinkles_cli
from wrinkles.output import complete_steps

REPO = Path(__file__).resolve().parents[1]
"""The repository root (tests run their subprocesses from there)."""
DROP_BLOCK = REPO / "scenes" / "drop_block.toml"
"""The falling block: body only, fast."""
DEFAULT_SCENE = REPO / "scenes" / "default.toml"
"""The compressed bar with a stiff skin (wrinkles)."""
EXTERNAL_MESHES = REPO.parent / "shared" / "meshes_external"
"""Meshes written by other projects (``../shared`` beside the checkout; never copied in)."""


wrinkles = wrinkles_cli
"""Run ``python -m wrinkles ARGS`` in a subprocess (:func:`validation.scene_runs.wrinkles_cli`)."""


def progress_lines(stdout: str) -> list[str]:
    """The per-frame progress lines of a run's standard output (set-up lines left out)."""
    return [line for line in stdout.splitlines() if line.startswith("frame ")]


def read_series(path: Path) -> tuple[np.ndarray, list[tuple[float, dict[str, np.ndarray]]]]:
    """Points and ``(time, point data)`` of every step of an XDMF time series (meshio)."""
    with meshio.xdmf.TimeSeriesReader(str(path)) as reader:
        points, _ = reader.read_points_cells()
        steps = [reader.read_data(k)[:2] for k in range(reader.num_steps)]
    return points, steps


def read_shell_series(path: Path) -> tuple[np.ndarray, np.ndarray, list[tuple[float, dict]]]:
    """Points, first cell block and ``(t, point_data)`` of every step (meshio)."""
    with meshio.xdmf.TimeSeriesReader(str(path)) as reader:
        points, cells = reader.read_points_cells()
        steps = [reader.read_data(k) for k in range(reader.num_steps)]
    return points, cells[0].data, [(t, pd) for t, pd, _ in steps]


SCENE = REPO / "scenes" / "ball_sofa_coarse.toml"


FAST = ["--set", "shell.subdivision.levels=1", "--set", "output.render=false"]


LENGTH, WIDTH = 0.12, 0.03
"""Length and side of the bar of :func:`bar_scene` [m]."""


def bar_scene(pin_velocity: tuple[float, float, float], frames: int,
              shell: dict[str, Any], nu: float = 0.45) -> dict[str, Any]:
    """A soft bar clamped at x = 0 and at x = LENGTH (that end moves with ``pin_velocity``)."""
    return {
        "mesh": {"builder": "box", "params": {"lx": LENGTH, "ly": WIDTH, "lz": WIDTH,
                                              "h": 0.015}},
        "material": {"model": "neo_hookean", "E": 5.0e4, "nu": nu},
        "body": {"dynamics": "static", "dt": 1.0, "gravity": [0.0, 0.0, 0.0],
                 "pins": [{"point": [0.0, 0.0, 0.0], "normal": [1.0, 0, 0]},
                          {"point": [LENGTH, 0.0, 0.0],
                           "normal": [1.0, 0, 0], "velocity": list(pin_velocity)}]},
        "time": {"frames": frames},
        "output": {"xdmf": False},
        "shell": shell,
    }


SKIN = {"E": 5.0e7, "nu": 0.3, "thickness": 5.0e-4}
"""Skin/body stiffness ratio 1000: wrinkle wavelength ~ 2.1 cm (Remillard & Kry sizing)."""


def dumps(document: dict[str, Any]) -> str:
    """Serialise a dict (scalars first, then one header per top-level table) as TOML."""
    lines = [f"{key(k)} = {inline(v)}" for k, v in document.items()
             if v is not None and not isinstance(v, dict)]
    for name, table in document.items():
        if isinstance(table, dict):
            lines.append(f"[{key(name)}]")
            lines += [f"{key(k)} = {inline(v)}" for k, v in table.items() if v is not None]
    return "\n".join(lines) + "\n"


def base_scene() -> dict[str, Any]:
    """A small valid scene (static P1 cube on a coarse box, 1 frame)."""
    return {"title": "reliability", "mesh": {"builder": "box",
                                             "params": {"lx": 0.1, "ly": 0.1, "lz": 0.1,
                                                        "h": 0.05}},
            "material": {"model": "neo_hookean", "E": 1e4, "nu": 0.3, "density": 1000.0},
            "body": {"degree": 1, "dynamics": "static", "dt": 1.0,
                     "gravity": [0.0, 0.0, -9.81],
                     "pins": [{"point": [0.0, 0.0, 0.0],
                               "normal": [0.0, 0.0, 1.0], "tol": 1e-6}]},
            "time": {"frames": 1}}


def cube_tets() -> tuple[np.ndarray, np.ndarray]:
    """The unit cube split into 6 positively oriented tets (Kuhn triangulation)."""
    points = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float)
    tets = np.array([[0, 1, 3, 7], [0, 1, 7, 5], [0, 5, 7, 4], [0, 3, 2, 7], [0, 2, 6, 7],
                     [0, 6, 4, 7]])
    vol = np.einsum("ij,ij->i", np.cross(points[tets[:, 1]] - points[tets[:, 0]],
                                         points[tets[:, 2]] - points[tets[:, 0]]),
                    points[tets[:, 3]] - points[tets[:, 0]])
    tets[vol < 0] = tets[vol < 0][:, [0, 1, 3, 2]]
    return points * 0.1, tets


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


BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def key(name: str) -> str:
    """A TOML key: bare when possible, else a quoted string."""
    return name if BARE_KEY.match(name) else json.dumps(name)


def inline(value: Any) -> str:
    """A TOML inline value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return ("nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
                if math.isinf(value) else repr(value))
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, dict):
        items = ", ".join(f"{key(k)} = {inline(v)}" for k, v in value.items() if v is not None)
        return "{ " + items + " }" if items else "{}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(inline(v) for v in value if v is not None) + "]"
    raise TypeError(f"no TOML form for {value!r}")


def energies(out: Path) -> np.ndarray:
    return np.array([r["energy"] for r in json.loads((out / "summary.json").read_text())
                     ["frames"]])


def load_script(path: Path) -> ModuleType:
    """Import a script (e.g. ``paper/make_paper.py``) as a module by its path."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None, path
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def folded_plate(angle: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 10 x 10 unit plate whose half x > 0.5 is turned by ``angle`` [rad] about x = 0.5.

    The turned half is also moved by (0, 0.037, 0.1) (the column of faces at the hinge
    stretches to hold it; off the grid's lines, so no edge crosses the other half exactly on
    one of its edges): past pi it passes through the other half. Returns ``(rest, faces, x)``.
    """
    from meshes.shells import grid_plate

    rest, faces = grid_plate(10, 10, 1.0, 1.0)
    x = rest.copy()
    right = x[:, 0] > 0.5 + 1e-12
    d = x[right, 0] - 0.5
    x[right, 0], x[right, 2] = 0.5 + d * np.cos(angle), d * np.sin(angle) + 0.1
    x[right, 1] += 0.037
    return rest, faces, x
