"""The scene: what one ``wrinkles run SCENE.toml`` simulates, as frozen dataclasses.

A scene file has one table per concern, each mapped by :mod:`wrinkles.config` onto the options
dataclass of the code that uses it::

    [mesh]      SceneMesh      -- gmsh builder + [mesh.params], or a tet mesh file
    [material]  Material       -- stored energy model, E, nu, density
    [body]      BodyOptions    -- degree, dynamics, dt, gravity; [[body.pins]], [[body.contacts]]
    [newton]    NewtonKeys     -- the body's Newton solver: rtol, expert options
    [time]      TimeOptions    -- number of frames, body steps per frame
    [output]    OutputOptions  -- which files, every N frames
    [shell]     ShellOptions   -- the embedded shell (absent = body only), wrinkles/shell_setup.py
    [rigid]     RigidKeys      -- rigid balls ([[rigid.balls]]) coupled two-way, models/rigid.py

Tables that are absent keep their defaults; optional physics is off unless the scene asks for
it: no ``[[body.contacts]]`` means no obstacle, no ``[[body.pins]]`` no pins, and
``body.dynamics`` defaults to ``"static"``.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from meshes.errors import InputError
from meshes.validate import MeshWarning
from models.body import BodyOptions
from models.materials import Material
from models.rigid import RigidBallOptions, RigidCouplingOptions, RigidOptions, scheme
from solvers.body_newton import NewtonOptions
from wrinkles.collective import world_root
from wrinkles.config import (
    Source,
    build,
    call_kwargs,
    expert,
    flatten,
    load,
    read_toml,
    to_dict,
    unflatten,
)
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
    output interval ``steps_per_frame * body.dt``, so a run ends at
    ``t = frames * steps_per_frame * body.dt``.

    Attributes:
        frames: number of frames (>= 1).
        steps_per_frame: body steps per frame (>= 1).

    """

    frames: int = 1
    steps_per_frame: int = 1

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise InputError(f"time.frames must be >= 1, got {self.frames}")
        if self.steps_per_frame < 1:
            raise InputError(f"time.steps_per_frame must be >= 1, got {self.steps_per_frame}")


@dataclass(frozen=True)
class NewtonKeys:
    """``[newton]``: the body's Newton solver, a tolerance and an expert mapping.

    Attributes:
        rtol: relative tolerance on the residual norm.
        options: expert mapping of the other fields of
            :class:`solvers.body_newton.NewtonOptions` (``atol``, ``max_it``,
            ``line_search_type``, ``max_halvings``, ...), including ``petsc``: PETSc options of
            the body's SNES / KSP / PC (``"petsc.ksp_type" = "gmres"``), set last, as dolfinx
            passes ``petsc_options``.

    """

    rtol: float = 1e-9
    options: dict[str, Any] = field(default_factory=dict)
    internals: NewtonOptions = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "options", flatten(unflatten(self.options, "newton.options")))
        if not (math.isfinite(self.rtol) and self.rtol >= 0.0):
            raise InputError(f"newton.rtol must be finite and >= 0, got {self.rtol}")
        object.__setattr__(self, "internals", expert(NewtonOptions, self.options,
                                                     "newton.options", {"rtol": self.rtol}))


@dataclass(frozen=True)
class RigidKeys:
    """``[rigid]``: the rigid balls and an expert mapping of their coupling iteration.

    Attributes:
        balls: the rigid balls (``[[rigid.balls]]``); each adds a sphere contact to the body.
        options: expert mapping of :class:`models.rigid.RigidCouplingOptions` (``rtol``,
            ``max_iterations`` of the per-step ball <-> body iteration).

    """

    balls: tuple[RigidBallOptions, ...] = ()
    options: dict[str, Any] = field(default_factory=dict)
    internals: RigidOptions = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "options", flatten(unflatten(self.options, "rigid.options")))
        coupling = expert(RigidCouplingOptions, self.options, "rigid.options")
        object.__setattr__(self, "internals", RigidOptions(balls=self.balls, coupling=coupling))


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
        time: frame count and body steps per frame.
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
    rigid: RigidKeys | None = None

    def __post_init__(self) -> None:
        if self.rigid is not None and self.rigid.balls:
            try:
                scheme(self.body.dynamics)
            except InputError as exc:
                raise InputError(f"rigid.balls: {exc}") from None
        if self.shell is not None and self.output.render and not self.output.xdmf:
            raise InputError("output.render = true draws the shell series, which output.xdmf "
                             "= false does not write: set output.render = false or "
                             "output.xdmf = true")


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

    ``body.gravity`` is ``-9.81 up``; the ``normal`` of a plane contact or a plane pin (a
    pin without ``box``) is ``up``. Keys written in the file (or ``--set``) are left as they are.

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
    for key in ("contacts", "pins"):
        for entry in body.get(key, []) if isinstance(body.get(key), list) else []:
            if not isinstance(entry, dict) or "box" in entry:
                continue
            if entry.get("obstacle", "plane") == "plane":
                entry.setdefault("normal", list(e))


RETIRED: dict[str, str] = {
    "time.end_time": "give time.frames (the run ends at frames * steps_per_frame * body.dt)",
    "newton.atol": "set it in [newton.options] (atol = ...)",
    "newton.max_it": "set it in [newton.options] (max_it = ...)",
    "body.quadrature_degree": "the volume quadrature degree is 2 * body.degree",
    "body.pins[].kind": "a pin with 'box' selects a box, one without it the plane through "
                        "'point' with 'normal'",
    "body.pins[].box_min": "give box = [[xmin, ymin, zmin], [xmax, ymax, zmax]]",
    "body.pins[].box_max": "give box = [[xmin, ymin, zmin], [xmax, ymax, zmax]]",
    "body.pins[].value": "a pin starts at rest: give its velocity",
    "body.pins[].angle": "a pin starts at rest: give its angular_velocity",
    "body.pins[].axis": "give angular_velocity as a vector along the axis",
    "body.pins[].center": "the rotation axis passes through the pin's 'point'",
    "body.contacts[].center": "a sphere's centre is its 'point'",
    "body.contacts[].stiffness": "give body.contact_stiffness (one for all contacts)",
    "body.contacts[].stiffness_factor": "give body.contact_stiffness [Pa/m]",
    "body.contacts[].quadrature_degree": "the facet quadrature is fixed per obstacle shape",
    "rigid.balls[].density": "give the ball's mass [kg]",
    "rigid.balls[].stiffness": "give body.contact_stiffness (one for all contacts)",
    "rigid.balls[].stiffness_factor": "give body.contact_stiffness [Pa/m]",
    "rigid.balls[].quadrature_degree": "the facet quadrature is fixed per obstacle shape",
    "rigid.coupling": "set rtol / max_iterations in [rigid.options]",
    "output.checkpoint": "checkpoint.h5 is always written",
    "shell.solver.hessian": "set it in [shell.solver.options] (\"energy.hessian_mode\" = ...)",
}
"""Keys of earlier scene files that are refused with what replaces them (other unknown keys
get the loader's closest-key hint)."""


def refuse_retired(doc: dict[str, Any], where: str = "<dict>") -> None:
    """Refuse a key of :data:`RETIRED` in the document, naming the key and its replacement.

    Raises:
        InputError: ``where: <dotted key>: no longer a scene key; <hint>``.

    """
    def walk(table: Any, prefix: str, pattern: str) -> None:
        if isinstance(table, list):
            for i, entry in enumerate(table):
                walk(entry, f"{prefix}[{i}]", f"{pattern}[]")
            return
        if not isinstance(table, dict):
            return
        for key, value in table.items():
            dotted, shape = f"{prefix}.{key}".lstrip("."), f"{pattern}.{key}".lstrip(".")
            hint = RETIRED.get(shape)
            if hint:
                raise InputError(f"{where}: {dotted}: no longer a scene key; {hint}")
            walk(value, dotted, shape)

    walk(doc, "", "")


def load_scene(path: str | Path, overrides: list[str] | None = None) -> Scene:
    """Load and validate a scene file with ``--set key=value`` overrides.

    Raises:
        InputError: naming the file and dotted key of the first problem found.

    """
    path = Path(path)
    scene = load(Scene, path, overrides, overlays=(refuse_retired, apply_up))
    keys = frozenset(o.partition("=")[0].strip() for o in overrides or [])
    warn_added_tables(path, keys)
    return resolve(scene, path.resolve().parent, Source(path.name, keys))


OPTIONAL_TABLES: tuple[str, ...] = ("shell", "rigid")
"""Tables whose presence adds a part to the scene (the embedded shell, rigid balls)."""


def warn_added_tables(path: Path, keys: frozenset[str]) -> None:
    """Warn when a ``--set`` key creates an :data:`OPTIONAL_TABLES` table the file lacks.

    ``--set shell.imperfection_seed=2`` on a body-only scene adds a whole shell with the
    defaults of every other key: what the user asked for, or a key meant for another scene.
    Rank 0 warns (every rank loads the scene).
    """
    if not world_root():
        return
    written = read_toml(path)
    for table in OPTIONAL_TABLES:
        added = sorted(k for k in keys if k == table or k.startswith(f"{table}."))
        if added and table not in written:
            warnings.warn(f"--set {added[0]}: {path.name} has no [{table}] table; the override "
                          f"adds one, with the defaults for its other keys", MeshWarning,
                          stacklevel=2)


def scene_from_dict(data: dict[str, Any], base: Path, name: str = "<dict>") -> Scene:
    """Build a scene from a plain dict (e.g. the ``scene`` entry of ``summary.json``)."""
    src = Source(name)
    data = copy.deepcopy(data)
    refuse_retired(data, name)
    apply_up(data, name)
    return resolve(build(Scene, data, "", src), base, src)


def with_frames(scene: Scene, frames: int) -> Scene:
    """Return the scene with ``time.frames`` replaced (the ``--frames`` option)."""
    try:
        time = dataclasses.replace(scene.time, frames=frames)
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

