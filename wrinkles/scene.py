"""The scene: what one ``wrinkles run SCENE.toml`` simulates, as frozen dataclasses.

A scene file has one table per concern, each mapped by :mod:`wrinkles.config` onto the options
dataclass of the code that uses it::

    [mesh]      SceneMesh      -- gmsh builder + [mesh.params], or a tet mesh file
    [material]  Material       -- stored energy model, E, nu, density
    [body]      BodyOptions    -- degree, dynamics, dt, gravity; [[body.pins]], [[body.contacts]]
    [newton]    NewtonOptions  -- tolerances of the body's Newton solver
    [time]      TimeOptions    -- number of frames (or end time), body steps per frame
    [output]    OutputOptions  -- which files, every N frames
    [shell]     ShellOptions   -- the embedded shell (absent = body only), wrinkles/shell_setup.py
    [rigid]     RigidOptions   -- rigid balls ([[rigid.balls]]) coupled two-way, models/rigid.py

Tables that are absent keep their defaults; optional physics is off unless the scene asks for
it: no ``[[body.contacts]]`` means no obstacle, no ``[[body.pins]]`` no pins, and
``body.dynamics`` defaults to ``"static"``.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from meshes.errors import InputError
from models.body import BodyOptions
from models.materials import Material
from models.rigid import RigidOptions, scheme
from solvers.body_newton import NewtonOptions
from wrinkles.config import Source, build, call_kwargs, expert, flatten, load, to_dict, unflatten
from wrinkles.output import OutputOptions
from wrinkles.shell_setup import ShellOptions

BUILDERS: tuple[str, ...] = ("box", "cylinder", "sphere", "sofa")
"""Names of the gmsh mesh builders a scene may use (functions of the ``meshes`` package)."""


@dataclass(frozen=True)
class SceneMesh:
    """The coarse tetrahedral body mesh: a gmsh builder with parameters, or a file.

    Attributes:
        builder: name of a builder in ``meshes`` (``box``, ``cylinder``, ``sphere``,
            ``sofa``); empty when ``file`` is given.
        params: keyword arguments of the builder (lengths in metres), checked against the
            builder's signature when the scene is loaded.
        file: path of a tet mesh file read by ``meshes.load`` (any format meshio reads);
            relative paths are relative to the scene file. Empty when ``builder`` is given.

    """

    builder: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    file: str = ""

    def __post_init__(self) -> None:
        if bool(self.builder) == bool(self.file):
            raise InputError("give exactly one of 'mesh.builder' or 'mesh.file'")
        if self.builder and self.builder not in BUILDERS:
            raise InputError(f"mesh.builder must be one of {BUILDERS}, got {self.builder!r}")
        if self.file and self.params:
            raise InputError("mesh.params only applies to a builder, not to a mesh file")


@dataclass(frozen=True)
class TimeOptions:
    """The frame loop: each frame advances the body by ``steps_per_frame`` steps of ``body.dt``.

    The time step itself belongs to the body's integrator (``body.dt``); a frame is the
    output interval ``steps_per_frame * body.dt``.

    Attributes:
        frames: number of frames; ``None`` to derive it from ``end_time``.
        end_time: final time [s]; frames = ceil(end_time / frame interval). At most one of
            ``frames`` and ``end_time`` may be given; with neither, a single frame is run.
        steps_per_frame: body steps per frame (>= 1).

    """

    frames: int | None = None
    end_time: float | None = None
    steps_per_frame: int = 1

    def __post_init__(self) -> None:
        if self.frames is not None and self.end_time is not None:
            raise InputError("give either 'time.frames' or 'time.end_time', not both")
        if self.frames is not None and self.frames < 1:
            raise InputError(f"time.frames must be >= 1, got {self.frames}")
        if self.end_time is not None and not self.end_time > 0.0:
            raise InputError(f"time.end_time must be > 0, got {self.end_time}")
        if self.steps_per_frame < 1:
            raise InputError(f"time.steps_per_frame must be >= 1, got {self.steps_per_frame}")

    def n_frames(self, dt: float) -> int:
        """Return the number of frames to run with body time step ``dt`` [s]."""
        if self.frames is not None:
            return self.frames
        if self.end_time is not None:
            return max(1, math.ceil(self.end_time / (dt * self.steps_per_frame) - 1e-9))
        return 1


@dataclass(frozen=True)
class NewtonKeys:
    """``[newton]``: the body's Newton solver, named keys and an expert mapping.

    Attributes:
        rtol: relative tolerance on the residual norm.
        atol: absolute tolerance on the residual norm [N].
        max_it: Newton iterations per solve.
        options: expert mapping of the other fields of
            :class:`solvers.body_newton.NewtonOptions` (``line_search_type``, ``max_halvings``,
            ...), including ``petsc``: PETSc options of the body's SNES / KSP / PC
            (``"petsc.ksp_type" = "gmres"``), set last, as dolfinx passes ``petsc_options``.

    """

    rtol: float = 1e-9
    atol: float = 1e-10
    max_it: int = 50
    options: dict[str, Any] = field(default_factory=dict)
    internals: NewtonOptions = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "options", flatten(unflatten(self.options, "newton.options")))
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"newton.{name} must be finite and >= 0, got {value}")
        if self.max_it < 1:
            raise InputError(f"newton.max_it must be >= 1, got {self.max_it}")
        named = {"rtol": self.rtol, "atol": self.atol, "max_it": self.max_it}
        object.__setattr__(self, "internals",
                           expert(NewtonOptions, self.options, "newton.options", named))


@dataclass(frozen=True)
class Scene:
    """Everything one run simulates (the root table of a scene file).

    Attributes:
        mesh: the coarse body mesh (required).
        title: free text shown in the summary.
        up: the mesh's up axis ("z" by default; meshes from other tools are often "y"):
            gravity, plane contact and pin normals default to it (:func:`apply_up`) and the
            renders and the ParaView view stand on it.
        material: the body's hyperelastic material.
        body: the body's discretisation, dynamics, time step, gravity, pins and contacts.
        newton: the body's Newton solver.
        time: frame count (or end time) and body steps per frame.
        output: output files and their frequency.
        shell: the embedded shell and its coupling; ``None`` (no ``[shell]`` table) runs the
            body only.
        rigid: rigid balls that fall onto the body (each adds a sphere contact after the
            ``[[body.contacts]]``) and their coupling; ``None`` (no ``[rigid]`` table): none.
            Needs ``body.dynamics`` implicit Euler or Newmark (the balls use the same scheme).

    """

    mesh: SceneMesh
    title: str = ""
    up: Literal["x", "y", "z"] = "z"
    material: Material = field(default_factory=Material)
    body: BodyOptions = field(default_factory=BodyOptions)
    newton: NewtonKeys = field(default_factory=NewtonKeys)
    time: TimeOptions = field(default_factory=TimeOptions)
    output: OutputOptions = field(default_factory=OutputOptions)
    shell: ShellOptions | None = None
    rigid: RigidOptions | None = None

    def __post_init__(self) -> None:
        if self.rigid is not None and self.rigid.balls:
            try:
                scheme(self.body.dynamics)
            except InputError as exc:
                raise InputError(f"rigid.balls: {exc}") from None


# --------------------------------------------------------------------------------------------
# Loading and resolving


def mesh_builder(name: str) -> Callable[..., Any]:
    """Return the builder function ``meshes.builders.<name>``."""
    return getattr(importlib.import_module("meshes.builders"), name)


def _resolve_mesh(mesh: SceneMesh, base: Path, src: Source) -> SceneMesh:
    """Type-check builder params against the builder signature; make a file path absolute."""
    if mesh.builder:
        params = call_kwargs(mesh_builder(mesh.builder), mesh.params, "mesh.params", src,
                             skip=("cache",))
        return dataclasses.replace(mesh, params=params)
    path = Path(mesh.file).expanduser()
    if not path.is_absolute():
        path = (Path.cwd() if "mesh.file" in src.overridden else base) / path
    if not path.is_file():
        raise src.error("mesh.file", f"no such mesh file '{path}'")
    return dataclasses.replace(mesh, file=str(path.resolve()))


def resolve(scene: Scene, base: Path, src: Source) -> Scene:
    """Run the checks that need the file system or a builder signature (mesh params/file)."""
    return dataclasses.replace(scene, mesh=_resolve_mesh(scene.mesh, base, src))


UP_AXES: dict[str, tuple[float, float, float]] = {
    "x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
"""The scene's ``up`` axis -> its unit vector."""
STANDARD_GRAVITY = 9.81
"""Default gravity [m/s^2], along minus the scene's ``up`` axis."""


def apply_up(doc: dict[str, Any], where: str = "<dict>") -> None:
    """Fill the defaults that follow ``up`` into the document, where absent (in place).

    ``body.gravity`` is ``-9.81 up``; the ``normal`` of a plane contact or a plane pin is
    ``up``. Keys written in the file (or ``--set``) are left as they are.

    Raises:
        InputError: ``up`` is not one of ``"x"``, ``"y"``, ``"z"``.

    """
    up = doc.get("up", "z")
    if not isinstance(up, str) or up not in UP_AXES:
        raise InputError(f"{where}: up: must be one of 'x', 'y', 'z', got {up!r}")
    e = list(UP_AXES[up])
    body = doc.setdefault("body", {}) if up != "z" or "body" in doc else None
    if not isinstance(body, dict):
        return
    if up != "z":
        body.setdefault("gravity", [-STANDARD_GRAVITY * c if c else 0.0 for c in e])
    for key, kind in (("contacts", "obstacle"), ("pins", "kind")):
        for entry in body.get(key, []) if isinstance(body.get(key), list) else []:
            if isinstance(entry, dict) and entry.get(kind, "plane") == "plane":
                entry.setdefault("normal", list(e))


def load_scene(path: str | Path, overrides: list[str] | None = None) -> Scene:
    """Load and validate a scene file with ``--set key=value`` overrides.

    Raises:
        InputError: naming the file and dotted key of the first problem found.

    """
    path = Path(path)
    scene = load(Scene, path, overrides, overlays=(apply_up,))
    keys = frozenset(o.partition("=")[0].strip() for o in overrides or [])
    return resolve(scene, path.resolve().parent, Source(path.name, keys))


def scene_from_dict(data: dict[str, Any], base: Path, name: str = "<dict>") -> Scene:
    """Build a scene from a plain dict (e.g. the ``scene`` entry of ``summary.json``)."""
    src = Source(name)
    data = copy.deepcopy(data)
    apply_up(data, name)
    return resolve(build(Scene, data, "", src), base, src)


def with_frames(scene: Scene, frames: int) -> Scene:
    """Return the scene with ``time.frames`` replaced (the ``--frames`` option)."""
    try:
        time = dataclasses.replace(scene.time, frames=frames, end_time=None)
    except InputError as exc:
        raise InputError(f"--frames: {exc}") from None
    return dataclasses.replace(scene, time=time)


def scene_dict(scene: Scene) -> dict[str, Any]:
    """Return the resolved scene as JSON-able data (round-trips via :func:`scene_from_dict`).

    ``rigid`` appears only when the scene has a ``[rigid]`` table, so the summaries of scenes
    without rigid bodies keep their layout (and restart from runs of earlier versions).
    """
    data: dict[str, Any] = to_dict(scene)
    if data.get("rigid") is None:
        data.pop("rigid", None)
    return data

