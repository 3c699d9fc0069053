"""Set-up of the embedded shell (Algorithm 1 of the draft; Remillard & Kry 2013).

Once per run: the outward boundary surface of the body mesh is subdivided ``L`` levels into the
shell T (rest shape X_T); the embedding matrix B maps the body's displacement space onto T's
vertices; clusters give the constraint matrix H; the shell energy

    W(x) = k_L W_L + k_A W_A + k_B W_B + k_P ||H (x - y)||^2

and its Newton solver are built. The stiffnesses come either from ``[shell.energy]`` (``k_*``
directly) or from the physical skin ``[shell.skin]`` (E, nu, thickness ->
:mod:`models.shell.stiffness`; bending calibrated "cylinder", ``k_B = D / 6``, since wrinkles
are cylindrical bends). With a skin and no explicit cluster count or spacing, the clusters are
sized from the skin's wrinkle wavelength on the body material,
``lambda = 2 pi h (Ebar_f / (3 Ebar_s))^(1/3)`` (sigma = lambda/pi, r = lambda/2).
The per-frame solve is :mod:`wrinkles.shell_stage`.
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from meshes.errors import InputError
from meshes.validate import MeshWarning
from models.backend import MPI
from models.coupling import PenaltyCoupling
from models.embedding.caps import flip_caps
from models.embedding.clusters import (
    ClusterOptions,
    Clusters,
    build_clusters,
    cluster_sizing,
    wrinkle_wavelength,
)
from models.embedding.embedding import (
    Embedding,
    EmbeddingOptions,
    build_embedding,
    mesh_surface,
)
from models.embedding.subdivision import Subdivision, SubdivisionOptions, subdivide
from models.materials import Material
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState, vertex_normals
from models.shell.self_intersection import intersecting_faces
from models.shell.stiffness import ShellMaterial, shell_stiffness
from models.shell.topology import ShellTopology
from solvers.body import Body
from solvers.coupling import CouplingOptions
from solvers.decomposition.patch_energy import ShellProblem
from solvers.decomposition.split_newton import SplitNewtonSolver
from solvers.multigrid import ShellHierarchy
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver
from solvers.solver_choice import (
    choose_factor_reuse,
    choose_joint_split,
    choose_linear_method,
    choose_phase_space,
    choose_shift_schedule,
    choose_threads,
)
from wrinkles.config import expert, flatten, to_dict, unflatten


@dataclass(frozen=True)
class SkinOptions:
    """Physical skin replacing ``k_L``, ``k_A``, ``k_B`` of ``[shell.energy]``.

    Attributes:
        E: Young's modulus of the skin E_f [Pa].
        nu: Poisson ratio of the skin.
        thickness: skin thickness h [m].
        membrane: membrane mapping of :func:`models.shell.stiffness.membrane_stiffness`
            ("equibiaxial" or "isotropic", the latter needs nu >= 1/3).
        bending: bending calibration: "cylinder" (k_B = D/6, for wrinkles) or "sphere"
            (k_B = D/2), D = E h^3 / (12 (1 - nu^2)).

    """

    E: float = 1.0e7
    nu: float = 0.3
    thickness: float = 1.0e-3
    membrane: Literal["equibiaxial", "isotropic"] = "equibiaxial"
    bending: Literal["sphere", "cylinder"] = "cylinder"

    def __post_init__(self) -> None:
        for name in ("E", "thickness"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise InputError(f"shell.skin.{name}: must be > 0, got {getattr(self, name)}")
        if not -1.0 < self.nu < 0.5:
            raise InputError(f"shell.skin.nu: must be in (-1, 0.5), got {self.nu}")


def _positive(table: object, names: tuple[str, ...], prefix: str) -> None:
    """Refuse a given (not None) value of ``names`` that is not finite and > 0."""
    for name in names:
        value = getattr(table, name)
        if value is not None and not (np.isfinite(value) and value > 0.0):
            raise InputError(f"{prefix}.{name}: must be > 0, got {value}")


@dataclass(frozen=True)
class SubdivisionKeys:
    """``[shell.subdivision]``: how the body's surface is refined into the shell.

    Attributes:
        levels: subdivision levels L (each x4 triangles), >= 0.
        scheme: "linear" (1-to-4 midpoint) or "loop".

    """

    levels: int = 1
    scheme: Literal["linear", "loop"] = "linear"

    def __post_init__(self) -> None:
        if self.levels < 0:
            raise InputError(f"subdivision.levels: must be >= 0, got {self.levels}")


@dataclass(frozen=True)
class ClusterKeys:
    """``[shell.clusters]``: the Gaussian clusters of the penalty (Remillard & Kry 2013).

    With none of the keys and a ``[shell.skin]`` the clusters are sized from the skin's wrinkle
    wavelength on the body (:func:`cluster_options`).

    Attributes:
        count: number of clusters c.
        spacing: centre spacing r [m] (alternative to ``count``).
        sigma: Gaussian width [m] (default: from the spacing).

    """

    count: int | None = None
    spacing: float | None = None
    sigma: float | None = None

    def __post_init__(self) -> None:
        if self.count is not None and self.count < 1:
            raise InputError(f"clusters.count: must be >= 1, got {self.count}")
        _positive(self, ("spacing", "sigma"), "clusters")


@dataclass(frozen=True)
class EnergyKeys:
    """``[shell.energy]``: the stiffnesses of ``W = k_L W_L + k_A W_A + k_B W_B + k_P W_P``.

    ``k_L``, ``k_A``, ``k_B`` come from ``[shell.skin]`` when the scene has one (then they may not
    be given here); ``None`` keeps :class:`models.shell.energy.ShellParams`' default.

    Attributes:
        k_L: edge membrane stiffness [N/m x m].
        k_A: area membrane stiffness [N/m].
        k_B: hinge bending stiffness [N m].
        k_P: cluster penalty stiffness [N/m].

    """

    k_L: float | None = None
    k_A: float | None = None
    k_B: float | None = None
    k_P: float | None = None

    def __post_init__(self) -> None:
        for name in ("k_L", "k_A", "k_B", "k_P"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value >= 0.0):
                raise InputError(f"energy.{name}: must be finite and >= 0, got {value}")


@dataclass(frozen=True)
class CouplingKeys:
    """``[shell.coupling]``: whether the shell acts back on the body.

    Attributes:
        mode: "one_way" (the shell follows the body) or "two_way".

    """

    mode: Literal["one_way", "two_way"] = "one_way"


@dataclass(frozen=True)
class SolverKeys:
    """``[shell.solver]``: how the shell is solved: a few named choices and an expert mapping.

    Attributes:
        method: linear solves of the Newton steps: "auto" (by the shell's size, levels and
            load, :func:`solvers.solver_choice.choose_linear_method`), "direct" (sparse
            LDL^T) or "multigrid" (CG with geometric multigrid on the subdivision hierarchy).
        rtol: relative gradient tolerance of each frame's Newton solve.
        max_iterations: Newton iterations per frame.
        threads: threads of the element kernels and multigrid products; 0 = the cores of a
            serial run of a large shell, else 1 (:func:`solvers.solver_choice.choose_threads`).
        layout: how a one-way scene uses the ranks of ``mpiexec -n 2``: "split" (body and
            shell each split over both ranks, stage after stage), "overlap" (the body on one
            rank, the shell on the other, the stages overlapped: :mod:`wrinkles.overlap`) or
            "auto" (overlap where the body is a large share of the frame and too small to
            divide, :func:`wrinkles.overlap.choose_layout`). Other rank counts and two-way
            scenes split.
        options: expert mapping of dotted paths into :class:`ShellInternals` (``"newton.shift.
            growth" = 5``, ``"energy.hessian_mode" = "gauss_newton"``, ``"coupling.scheme" =
            "implicit"``), checked like any key; ``wrinkles check`` prints the resolved values.

    """

    method: Literal["auto", "direct", "multigrid"] = "auto"
    rtol: float = 1e-8
    max_iterations: int = 200
    threads: int = 0
    layout: Literal["auto", "split", "overlap"] = "auto"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "options", flatten(unflatten(self.options, "solver.options")))
        _positive(self, ("rtol",), "solver")
        if self.max_iterations < 1:
            raise InputError(f"solver.max_iterations: must be >= 1, got {self.max_iterations}")
        if self.threads < 0:
            raise InputError(f"solver.threads: must be 0 (auto) or >= 1, got {self.threads}")


@dataclass(frozen=True)
class ShellInternals:
    """Every option of the shell's set-up and solvers.

    The scene's named keys fill some of it, ``[shell.solver.options]`` the rest.

    Attributes:
        newton: the Newton solver (linear solvers, shifts, multigrid, modified Newton).
        energy: stiffnesses, flip barrier, Hessian mode and penalty Hessian form, threads.
        embedding: point location tolerances of B.
        clusters: placement method and sizing of the clusters.
        subdivision: levels, scheme and Loop weights.
        coupling: the two-way scheme (monolithic, or the fixed point: tolerance, cap, memory).

    """

    newton: ShellNewtonOptions = field(default_factory=ShellNewtonOptions)
    energy: ShellParams = field(default_factory=ShellParams)
    embedding: EmbeddingOptions = field(default_factory=EmbeddingOptions)
    clusters: ClusterOptions = field(default_factory=ClusterOptions)
    subdivision: SubdivisionOptions = field(default_factory=SubdivisionOptions)
    coupling: CouplingOptions = field(default_factory=CouplingOptions)


SCENE_DEFAULTS: dict[str, Any] = {
    "energy.penalty_hessian": "low_rank",
    "newton.multigrid.forcing": "eisenstat_walker",
    "newton.multigrid.rtol": 1e-4,
    "newton.multigrid.level_format": "sbaij",
    "newton.multigrid.eigen_estimate": "solve",
    "newton.multigrid.fallback": False,
    "newton.inertia_restart": True,
}
"""Internal values a scene starts from where they differ from the dataclass defaults (an
expert key may change them): the low-rank penalty, since ``H^T H`` fills in at large sizes;
the multigrid-CG settings measured fastest on the product's frames (inexact Newton with
Eisenstat-Walker forcing down to 1e-4, symmetric block level matrices, Chebyshev bounds once
per solve, no direct fallback; the first iteration of a warm started direct solve restarting
its shift ladder from a Lanczos estimate; docs/notes/solver-choice.md). The wrinkle-phase
coarse space is chosen by size and the shift ladder by the load (:data:`PHASE_SPACE_KEY`,
:func:`resolve_solver`)."""

PHASE_SPACE_KEY: str = "newton.multigrid.phase_space"
"""The expert key of the multigrid's wrinkle-phase coarse space; when a scene does not set it,
:func:`resolve_solver` sets it by the shell's size
(:func:`solvers.solver_choice.choose_phase_space`)."""


@dataclass(frozen=True)
class ShellOptions:
    """The ``[shell]`` table of a scene: the embedded shell and its coupling.

    Physics (what the shell is): ``subdivision``, ``clusters``, ``energy``, ``skin``,
    ``coupling``, ``imperfection``, ``imperfection_seed``; solver (how it is solved):
    ``solver``. The resolved internal options are :attr:`internals` (built when the table is
    read, so a bad expert key is refused then).

    Attributes:
        subdivision: levels and scheme of the surface subdivision.
        clusters: cluster count, spacing or width (default: physical sizing from the skin).
        energy: stiffnesses k_L, k_A, k_B, k_P.
        skin: physical skin; when given it sets k_L, k_A, k_B and the physical cluster sizing.
        coupling: one-way (default) or two-way coupling with the body.
        solver: the named solver choices and the expert mapping.
        imperfection: amplitude of the deterministic warm-start perturbation along the rest
            normals, as a fraction of the mean rest edge length (0 = none).
        imperfection_seed: which realisation of that perturbation (an integer >= 0; 0 is the
            one of earlier versions). A wrinkle pattern is one of many nearly equal minima and
            the perturbation picks it: runs over several seeds give the spread of energies,
            wavelengths and solver iterations of a scene (``benchmarks/product_frames.py
            --seeds``).

    """

    subdivision: SubdivisionKeys = field(default_factory=SubdivisionKeys)
    clusters: ClusterKeys = field(default_factory=ClusterKeys)
    energy: EnergyKeys = field(default_factory=EnergyKeys)
    skin: SkinOptions | None = None
    coupling: CouplingKeys = field(default_factory=CouplingKeys)
    solver: SolverKeys = field(default_factory=SolverKeys)
    imperfection: float = 1.0e-3
    imperfection_seed: int = 0
    internals: ShellInternals = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.imperfection) and self.imperfection >= 0.0):
            raise InputError(f"shell.imperfection: must be >= 0, got {self.imperfection}")
        if self.imperfection_seed < 0:
            raise InputError(f"shell.imperfection_seed: must be >= 0, got "
                             f"{self.imperfection_seed}")
        if self.skin is not None:
            for name in ("k_L", "k_A", "k_B"):
                if getattr(self.energy, name) is not None:
                    raise InputError(f"shell.energy.{name}: [shell.skin] sets it; give one of "
                                     f"the two")
        object.__setattr__(self, "internals", expert(
            ShellInternals, self.solver.options, "shell.solver.options",
            named=self.named_keys(), defaults=SCENE_DEFAULTS))

    @property
    def monolithic_two_way(self) -> bool:
        """Whether the shell is two-way coupled by the joint Newton solve (the default scheme)."""
        return self.coupling.mode == "two_way" and self.internals.coupling.scheme == "monolithic"

    def named_keys(self) -> dict[str, Any]:
        """Return the internal values the named keys set (dotted paths of ShellInternals)."""
        solver = self.solver
        keys: dict[str, Any] = {
            "subdivision.levels": self.subdivision.levels,
            "subdivision.scheme": self.subdivision.scheme,
            "coupling.mode": self.coupling.mode,
            "newton.rtol": solver.rtol, "newton.max_iterations": solver.max_iterations}
        if solver.method != "auto":  # resolved by resolve_solver once the size is known
            keys["newton.linear_method"] = solver.method
        if solver.threads:
            keys["energy.threads"] = keys["newton.multigrid.threads"] = solver.threads
        for table, prefix in ((self.clusters, "clusters"), (self.energy, "energy")):
            for f in dataclasses.fields(table):
                value = getattr(table, f.name)
                if value is not None:
                    keys[f"{prefix}.{f.name}"] = value
        return keys


def resolve_solver(options: ShellOptions, vertices: int, ranks: int, *,
                   static: bool) -> ShellOptions:
    """Return ``options`` with the solver choices made concrete for the shell and its load.

    "auto" becomes the method for a shell of ``vertices`` vertices, its subdivision levels and
    a ``static`` or dynamic load, threads 0 the count for that size and ``ranks``, an unset
    :data:`PHASE_SPACE_KEY` the phase-space choice for that size (none for the monolithic
    two-way step, whose joint CG does not use it), and each unset key of the shift ladder and
    of the factorisation reuse the one for the load (:mod:`solvers.solver_choice`); the
    internal options are rebuilt from them, so every later reader sees the choice. The vertex
    count is the whole shell's, so every rank count chooses alike.
    """
    by_load = {**choose_shift_schedule(static), **choose_factor_reuse(static)}
    chosen = {PHASE_SPACE_KEY: choose_phase_space(vertices) and not options.monolithic_two_way,
              **{f"newton.{key}": value for key, value in by_load.items()}}
    expert_keys = {**{key: value for key, value in chosen.items()
                      if key not in options.solver.options}, **options.solver.options}
    solver = dataclasses.replace(options.solver,
                                 method=choose_linear_method(options.solver.method, vertices,
                                                             options.subdivision.levels,
                                                             static=static),
                                 threads=choose_threads(options.solver.threads, ranks,
                                                        vertices),
                                 options=expert_keys)
    return options if solver == options.solver else dataclasses.replace(options, solver=solver)


def solver_facts(options: ShellOptions) -> dict[str, Any]:
    """Return the resolved solver choices a run records and ``wrinkles check`` prints."""
    newton = options.internals.newton
    return {"method": options.solver.method, "threads": options.solver.threads,
            "phase_space": newton.multigrid.phase_space,
            "shifts": f"x{newton.shift.growth:g} / {newton.shift_decay:g}",
            "factor_reuse": newton.modified.enabled}


def mean_edge_length(x: np.ndarray, topology: ShellTopology) -> float:
    """Mean length of the shell's edges [m]."""
    e = topology.edges
    return float(np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1).mean())


def shell_params(options: ShellOptions, edge_length: float) -> ShellParams:
    """``ShellParams`` of the scene: ``[shell.energy]``, or its k_P with the skin's k_L/k_A/k_B."""
    skin, params = options.skin, options.internals.energy
    if skin is None:
        return params
    mat = ShellMaterial(E=skin.E, nu=skin.nu, thickness=skin.thickness, edge_length=edge_length)
    k = shell_stiffness(mat, skin.membrane, skin.bending)
    return dataclasses.replace(params, k_L=k["k_L"], k_A=k["k_A"], k_B=k["k_B"])


def cluster_options(options: ShellOptions, material: Material) -> ClusterOptions:
    """Cluster options, sized from the skin and the body material when asked to be physical.

    Physical sizing applies when a skin is given and the clusters have no count, spacing or
    skin thickness of their own.
    """
    c, skin = options.internals.clusters, options.skin
    if skin is None or c.count is not None or c.spacing is not None or c.skin_thickness:
        return c
    return dataclasses.replace(c, skin_thickness=skin.thickness, skin_E=skin.E, skin_nu=skin.nu,
                               body_E=material.E, body_nu=material.nu)


@dataclass
class Shell:
    """The embedded shell of a run and its state.

    Attributes:
        options: the ``[shell]`` options.
        topology: shell connectivity.
        rest: ``(n, 3)`` rest positions X_T (= B X_q).
        embedding: B for the body's displacement space.
        clusters: clusters, H and partition.
        energy: the shell energy (its target is the current y), whole on every rank.
        solver: the Newton solver (reused over frames): serial on one rank, split over the
            ranks otherwise (:func:`shell_solver`).
        x: ``(n, 3)`` current shell positions.
        y: ``(n, 3)`` current target.
        normals: ``(n, 3)`` rest vertex normals (imperfection direction).
        edge_length: mean rest edge length [m].
        gradient_scale: reference gradient norm of the relative tolerance (0 = not yet set).
        shifts: the Newton's shift memory after the last solve (``shift_state`` of the
            solver that ran it; checkpointed).
        facts: set-up numbers for the summary.
        force: ``(n, 3)`` penalty force ``f`` on the target, ``B^T f`` on the body (two-way
            coupling; zero otherwise).
        coupling: constant part of the implicit coupling term (built on first use,
            :func:`penalty_coupling`).
        start_repaired: vertices the last warm start pulled towards the target because a
            face was turned over against the target's normals (:func:`admissible_start`).
        hierarchy: the subdivision hierarchy the shell was built by (the multigrid's levels).

    """

    options: ShellOptions
    topology: ShellTopology
    rest: np.ndarray
    embedding: Embedding
    clusters: Clusters
    energy: ShellEnergy
    solver: ShellNewtonSolver | SplitNewtonSolver
    x: np.ndarray
    y: np.ndarray
    normals: np.ndarray
    edge_length: float
    gradient_scale: float = 0.0
    shifts: np.ndarray = field(default_factory=lambda: np.zeros(2))
    facts: dict[str, Any] = field(default_factory=dict)
    force: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    coupling: PenaltyCoupling | None = None
    start_repaired: int = 0
    hierarchy: ShellHierarchy | None = None
    _crossing: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False,
                                                            compare=False)

    def __post_init__(self) -> None:
        if self.force.shape != self.rest.shape:
            self.force = np.zeros_like(self.rest)

    @property
    def params(self) -> ShellParams:
        """The stiffnesses in use."""
        return self.energy.params

    def intersecting_faces(self) -> np.ndarray:
        """Face pairs of the current shell ``x`` that pass through each other, (P, 2).

        :func:`models.shell.self_intersection.intersecting_faces`, computed once per state
        (the frame's record and its output step ask for the same ``x``).
        """
        if self._crossing is None or not np.array_equal(self._crossing[0], self.x):
            self._crossing = (self.x.copy(), intersecting_faces(
                self.x, self.topology.faces, self.params.threads))
        return self._crossing[1]

    def set_target(self, y: np.ndarray) -> None:
        """Move the penalty target of the energy and of a split solver's local energies."""
        self.energy.set_target(y)
        if isinstance(self.solver, SplitNewtonSolver):
            self.solver.set_target(y)

    def follow_hinges(self, x: np.ndarray) -> None:
        """Follow the hinge angles to ``x`` (a solve's start) in the energy and a split solver.

        :meth:`models.shell.energy.ShellEnergy.follow_hinges`: a fold closing past
        flat-on-flat keeps a smooth bending energy.
        """
        self.energy.follow_hinges(x)
        if isinstance(self.solver, SplitNewtonSolver):
            self.solver.set_hinge_branch(self.energy.hinge_branch)


BYTES_PER_VERTEX: dict[str, float] = {"direct": 26e3, "multigrid": 9e3}
"""Peak memory per shell vertex of a run by linear method [bytes]: from the measured peaks of
``benchmarks/scaling.py`` (direct MUMPS 15 GiB at 640k vertices, multigrid-CG 10 GiB at
1.26M), rounded up."""


def shell_vertices(surface_faces: int, levels: int) -> int:
    """Return the vertex count of a closed surface of ``surface_faces`` faces, subdivided.

    Each of the ``levels`` subdivisions multiplies the faces by 4; a closed genus-0 triangle
    surface has ``V = F / 2 + 2`` vertices.
    """
    return surface_faces * 4**levels // 2 + 2


def available_memory() -> float:
    """Memory this machine can still give [bytes] (``MemAvailable``; else the total)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def check_memory(options: ShellOptions, surface_faces: int, ranks_here: int = 1, *,
                 static: bool) -> None:
    """Refuse a shell that would not fit in memory, before it is built.

    Every rank of this machine holds a whole shell (``ranks_here`` of them); the linear method
    is the one ``auto`` chooses for the shell and a ``static`` or dynamic load.

    Raises:
        InputError: naming ``shell.subdivision.levels``, the vertex count, the estimate and
            the memory available.

    """
    levels = options.subdivision.levels
    n = shell_vertices(surface_faces, levels)
    method = choose_linear_method(options.solver.method, n, levels, static=static)
    need = BYTES_PER_VERTEX[method] * n * ranks_here
    have = available_memory()
    if need > 0.9 * have:
        raise InputError(
            f"shell.subdivision.levels = {levels}: the shell would have about {n:,} vertices "
            f"and need about {need / 2**30:.1f} GiB ({method} solver, {ranks_here} rank(s) on "
            f"this machine), more than the {have / 2**30:.1f} GiB available; lower the levels "
            f"or coarsen the body mesh")


def refine(options: ShellOptions, vertices: np.ndarray, faces: np.ndarray
           ) -> tuple[Subdivision, ShellTopology, float]:
    """Subdivide the body surface into the shell: ``(subdivision, topology, mean edge)``."""
    sub = subdivide(vertices, faces, options.internals.subdivision)
    topology = ShellTopology.from_faces(sub.faces, sub.vertices.shape[0])
    return sub, topology, mean_edge_length(sub.vertices, topology)


def shell_report(options: ShellOptions, material: Material, vertices: np.ndarray,
                 faces: np.ndarray, *, static: bool, ranks: int = 1) -> dict[str, Any]:
    """Return the values a run will use for the shell over the body surface.

    What ``wrinkles check`` prints: the shell's size, mean edge length and memory estimate,
    the stiffnesses (from the skin when there is one), the cluster sizing, the linear method
    and threads chosen for ``ranks`` ranks, and every internal option (the shift ladder for a
    ``static`` or dynamic body). Subdivides the surface (after :func:`check_memory`), builds
    no clusters.
    """
    check_memory(options, faces.shape[0], static=static)
    sub, _, a = refine(options, vertices, faces)
    options = resolve_solver(options, sub.vertices.shape[0], ranks, static=static)
    params = shell_params(options, a)
    count, spacing, sigma = cluster_sizing(cluster_options(options, material), sub.vertices,
                                           sub.faces)
    n = sub.vertices.shape[0]
    return {"vertices": n, "faces": int(sub.faces.shape[0]), "mean_edge_length": a,
            "memory_estimate_gib": BYTES_PER_VERTEX[options.solver.method] * n / 2**30,
            "solver": solver_facts(options),
            "k_L": params.k_L, "k_A": params.k_A, "k_B": params.k_B, "k_P": params.k_P,
            "k_F": params.k_F,
            "clusters": {"count": count, "spacing": spacing, "sigma": sigma},
            "internals": flatten(to_dict(options.internals))}


MIN_EDGES_PER_WAVELENGTH: float = 4.0
"""Fewer shell edges per wrinkle wavelength cannot resolve the wrinkles (a warning)."""
MIN_CLUSTER_VERTICES: int = 7
"""Clusters of fewer vertices (median support) pin the wrinkles down (a warning)."""


def sizing_warnings(options: ShellOptions, clusters: Clusters, material: Material,
                    edge_length: float) -> list[str]:
    """Messages when the shell cannot resolve the wrinkles its skin makes, naming the keys."""
    out = []
    if options.skin is not None:
        lam = wrinkle_wavelength(options.skin.thickness, options.skin.E, options.skin.nu,
                                 material.E, material.nu)
        if lam < MIN_EDGES_PER_WAVELENGTH * edge_length:
            out.append(f"shell.subdivision.levels = {options.subdivision.levels}: the skin's "
                       f"wrinkle wavelength {lam:.3g} m spans only {lam / edge_length:.1f} shell "
                       f"edges (mean edge {edge_length:.3g} m; at least "
                       f"{MIN_EDGES_PER_WAVELENGTH:g} resolve it): raise the levels or "
                       f"shell.skin.thickness")
    support = np.diff(clusters.H.indptr)
    if support.size and np.median(support) < MIN_CLUSTER_VERTICES:
        out.append(f"shell.clusters: the median cluster holds {np.median(support):g} shell "
                   f"vertices (at least {MIN_CLUSTER_VERTICES} let wrinkles form under it): "
                   f"set a larger shell.clusters.spacing or a smaller count, or raise "
                   f"shell.subdivision.levels")
    return out


def shell_solver(energy: ShellEnergy, options: ShellNewtonOptions, hierarchy: ShellHierarchy,
                 clusters: Clusters, comm: MPI.Comm) -> ShellNewtonSolver | SplitNewtonSolver:
    """Return the shell's Newton solver for the ranks of ``comm`` (collective).

    One rank: :class:`solvers.shell_newton.ShellNewtonSolver`. More: the Newton split over
    the ranks (:class:`solvers.decomposition.split_newton.SplitNewtonSolver`), each rank
    owning the vertices of its share of the clusters (``clusters.partition`` merged to the
    rank count), with the same linear method: the distributed MUMPS LDL^T or the
    distributed multigrid CG (:mod:`solvers.decomposition.split_multigrid`, without the
    serial solver's wrinkle-phase coarse space).
    """
    if comm.size == 1:
        return ShellNewtonSolver(energy, options,  # type: ignore[arg-type]
                                 hierarchy=hierarchy)
    problem = ShellProblem(energy.topology, energy.rest, energy.params, clusters.H,
                           energy.target)
    return SplitNewtonSolver(problem, clusters.partition, options, comm,
                             prolongations=hierarchy.prolongations())


def build_shell(body: Body, options: ShellOptions, material: Material,
                log: Callable[[str], None] = lambda text: None, source: str = "the mesh") -> Shell:
    """Surface -> subdivision -> rest shell, B, clusters and H, energy and solver (collective).

    Every rank builds the same shell (the surface is gathered identically on all ranks; its
    cap slivers flipped, :mod:`models.embedding.caps`). A
    shell that would not fit in memory is refused first (:func:`check_memory`). ``log``
    announces each stage as it ends; a shell too coarse for its skin's wrinkles gets a
    :class:`meshes.MeshWarning` (:func:`sizing_warnings`); ``source`` names the body mesh in
    the refusal of a sliver surface triangle.
    """
    t0 = time.perf_counter()
    caps = flip_caps(mesh_surface(body.mesh))
    surface = caps.surface
    if caps.flips:
        log(f"shell: {caps.flips} cap sliver(s) of the body surface flipped (worst face quality "
            f"{caps.quality_before:.3g} -> {caps.quality_after:.3g}; the shell's rest surface "
            f"off the body's by at most {caps.moved:.3g} m)")
    local = body.mesh.comm.Split_type(MPI.COMM_TYPE_SHARED)
    static = body.options.dynamics == "static"
    check_memory(options, surface.faces.shape[0], local.size, static=static)
    local.Free()
    sub, topology, a = refine(options, surface.vertices, surface.faces)
    options = resolve_solver(options, sub.vertices.shape[0], body.mesh.comm.size,
                             static=static)
    log(f"shell: surface of {surface.faces.shape[0]} triangles subdivided "
        f"{options.subdivision.levels} times: {sub.vertices.shape[0]} vertices")
    emb = build_embedding(body.V, sub.vertices, options.internals.embedding)
    log("shell: embedding B")
    rest = np.ascontiguousarray(sub.vertices)
    sizing = cluster_options(options, material)
    clusters = build_clusters(rest, sub.faces, sizing)
    log(f"shell: {clusters.H.shape[0]} clusters")
    if body.mesh.comm.rank == 0:
        for message in sizing_warnings(options, clusters, material, a):
            warnings.warn(message, MeshWarning, stacklevel=2)
    params = shell_params(options, a)
    try:
        rest_state = RestState.from_positions(topology, rest)
    except InputError as exc:
        raise InputError(f"{source}: its surface makes a shell the solver cannot use ({exc}); "
                         f"remesh the body (mesh.file) or refine it (mesh.params.h)") from None
    energy = ShellEnergy(topology, rest_state, params, clusters.H)
    hierarchy = ShellHierarchy(sub)
    solver = shell_solver(energy, options.internals.newton, hierarchy, clusters, body.mesh.comm)
    ranks = body.mesh.comm.size
    split = f" split over {ranks} ranks" if ranks > 1 else ""
    if ranks > 1 and options.monolithic_two_way:
        joint = choose_joint_split(ranks, int(rest.shape[0]),
                                   options.internals.newton.linear_method)
        split += ("; the two-way joint system split as well" if joint else
                  "; the two-way joint system solved whole on every rank, the shell being small")
    log(f"shell: energy and solver ({options.solver.method}, {options.solver.threads} "
        f"thread(s){split})")
    facts = {"vertices": int(rest.shape[0]), "faces": int(sub.faces.shape[0]),
             "coarse_surface_vertices": int(surface.vertices.shape[0]),
             "cap_flips": caps.flips,
             "mean_edge_length": a, "solver": solver_facts(options),
             "k_L": params.k_L, "k_A": params.k_A,
             "k_B": params.k_B, "k_P": params.k_P,
             "clusters": dataclasses.asdict(clusters.report),
             "embedding": dataclasses.asdict(emb.report),
             "setup_time": time.perf_counter() - t0}
    return Shell(options, topology, rest, emb, clusters, energy, solver, rest.copy(),
                 rest.copy(), vertex_normals(rest, sub.faces), a, facts=facts,
                 hierarchy=hierarchy)


__all__ = ["Shell", "ShellOptions", "SkinOptions", "build_shell", "cluster_options",
           "shell_report",
           "mean_edge_length", "shell_params"]
