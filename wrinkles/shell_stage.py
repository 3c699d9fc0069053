"""The embedded-shell stage of the frame loop (Algorithm 1 of the draft; Remillard & Kry 2013).

Set-up, once: the outward boundary surface of the body mesh is subdivided ``L`` levels into
the shell T (its rest shape X_T); the embedding matrix B maps the body's displacement space
onto T's vertices; clusters give the constraint matrix H; the shell energy

    W(x) = k_L W_L + k_A W_A + k_B W_B + k_P ||H (x - y)||^2

and its Newton solver are built. Per frame, after the body step:

    y   = B (X_q + u_q) = X_T + B u_q                     (target; B reproduces X_q exactly)
    x_0 = x_prev + (y - y_prev) + eta_k                   (warm start moved with the body)
    x   = argmin W                                        (Newton on every rank, rank 0's x kept)

``eta_k`` is an optional tiny deterministic imperfection along the rest vertex normals
(``imperfection`` times the mean rest edge length, seeded by the frame number): a flat face
compressed exactly in its plane is a stationary point of W (the out-of-plane gradient is
zero), so without it a descent method never leaves the plane and no wrinkle can form.

The stiffnesses come either from ``[shell.energy]`` (``k_*`` directly) or from the physical
skin ``[shell.skin]`` (E, nu, thickness -> :mod:`models.shell.stiffness`). Wrinkles are
cylindrical bends, so the skin's bending stiffness uses the "cylinder" calibration
``k_B = D / 6`` by default (with ``k_B = D / 2`` a cylindrical bend costs 3x the plate energy
on equilateral meshes, measured by the shell engineers). With a skin and no explicit cluster
count or spacing, the clusters are sized from the wrinkle wavelength of the skin on the body
material, ``lambda = 2 pi h (Ebar_f / (3 Ebar_s))^(1/3)`` (sigma = lambda/pi, r = lambda/2).

The shell is solved redundantly on every rank and rank 0's result broadcast, so it is the same
on every rank and independent of the number of ranks (up to the body's own solver tolerance).
Two-way coupling (:mod:`models.coupling`) feeds the penalty force back to the body through
``B^T``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from models.backend import MPI
from models.body import Body
from models.coupling import (
    CouplingOptions,
    PenaltyCoupling,
    body_force_function,
    penalty_force,
)
from models.embedding.clusters import ClusterOptions, Clusters, build_clusters
from models.embedding.embedding import (
    Embedding,
    EmbeddingOptions,
    apply_to_function,
    build_embedding,
    mesh_surface,
)
from models.embedding.subdivision import SubdivisionOptions, subdivide
from models.errors import InputError, SolverError
from models.materials import Material
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState
from models.shell.stiffness import ShellMaterial, shell_stiffness
from models.shell.topology import ShellTopology
from solvers.multigrid import ShellHierarchy
from solvers.shell_newton import (
    ShellNewtonOptions,
    ShellNewtonSolver,
    ShellSolveError,
    ShellSolveReport,
)
from wrinkles.collective import on_root
from wrinkles.shell_output import SHELL_XDMF_NAME, ShellFrame, ShellSeries

StageRecord = dict[str, Any]


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


@dataclass(frozen=True)
class ShellOptions:
    """The ``[shell]`` table of a scene: the embedded shell and its coupling.

    Attributes:
        subdivision: levels and scheme (linear | loop) of the surface subdivision.
        clusters: cluster placement and sizing (count, spacing, or skin physics).
        energy: stiffnesses k_L, k_A, k_B, k_P and Hessian options (``ShellParams``).
        skin: physical skin; when given it sets k_L, k_A, k_B (k_P stays from ``energy``)
            and, without an explicit cluster count/spacing, the physical cluster sizing.
        newton: the shell's Newton solver (``ShellNewtonOptions``); with
            ``gradient_scale = 0`` the stage uses the largest initial gradient norm seen so
            far as the reference of ``rtol`` (warm-started frames are not over-solved).
        embedding: point location tolerances of B.
        coupling: one-way (default) or two-way coupling with the body.
        imperfection: amplitude of the deterministic warm-start perturbation along the rest
            normals, as a fraction of the mean rest edge length (0 = none).
        xdmf: write ``shell.xdmf`` + ``shell.h5`` (every frame the body series writes).
        render: after the run, write ``shell.png``, per-frame PNGs and ``shell.gif``
            (:mod:`wrinkles.render`).

    """

    subdivision: SubdivisionOptions = field(default_factory=SubdivisionOptions)
    clusters: ClusterOptions = field(default_factory=ClusterOptions)
    energy: ShellParams = field(default_factory=ShellParams)
    skin: SkinOptions | None = None
    newton: ShellNewtonOptions = field(default_factory=ShellNewtonOptions)
    embedding: EmbeddingOptions = field(default_factory=EmbeddingOptions)
    coupling: CouplingOptions = field(default_factory=CouplingOptions)
    imperfection: float = 1.0e-3
    xdmf: bool = True
    render: bool = False

    def __post_init__(self) -> None:
        if not (np.isfinite(self.imperfection) and self.imperfection >= 0.0):
            raise InputError(f"shell.imperfection: must be >= 0, got {self.imperfection}")


# --------------------------------------------------------------------------------------------
# Set-up


def mean_edge_length(x: np.ndarray, topology: ShellTopology) -> float:
    """Mean length of the shell's edges [m]."""
    e = topology.edges
    return float(np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1).mean())


def shell_params(options: ShellOptions, edge_length: float) -> ShellParams:
    """``ShellParams`` of the scene: ``[shell.energy]``, or its k_P with the skin's k_L/k_A/k_B."""
    skin = options.skin
    if skin is None:
        return options.energy
    mat = ShellMaterial(E=skin.E, nu=skin.nu, thickness=skin.thickness, edge_length=edge_length)
    k = shell_stiffness(mat, skin.membrane, skin.bending)
    return dataclasses.replace(options.energy, k_L=k["k_L"], k_A=k["k_A"], k_B=k["k_B"])


def cluster_options(options: ShellOptions, material: Material) -> ClusterOptions:
    """Cluster options, sized from the skin and the body material when asked to be physical.

    Physical sizing applies when a skin is given and the clusters have no count, spacing or
    skin thickness of their own.
    """
    c, skin = options.clusters, options.skin
    if skin is None or c.count is not None or c.spacing is not None or c.skin_thickness:
        return c
    return dataclasses.replace(c, skin_thickness=skin.thickness, skin_E=skin.E, skin_nu=skin.nu,
                               body_E=material.E, body_nu=material.nu)


def vertex_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Return unit area-weighted vertex normals of a triangle mesh (n, 3)."""
    a, b, c = (x[faces[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)
    n = np.zeros_like(x)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


@dataclass
class Shell:
    """The embedded shell of a run and its state.

    Attributes:
        options: the ``[shell]`` options.
        topology: shell connectivity.
        rest: ``(n, 3)`` rest positions X_T (= B X_q).
        embedding: B for the body's displacement space.
        clusters: clusters, H and partition.
        energy: the shell energy (its target is the current y).
        solver: the Newton solver (reused over frames).
        x: ``(n, 3)`` current shell positions.
        y: ``(n, 3)`` current target.
        normals: ``(n, 3)`` rest vertex normals (imperfection direction).
        edge_length: mean rest edge length [m].
        gradient_scale: reference gradient norm of the relative tolerance (0 = not yet set).
        facts: set-up numbers for the summary.
        force: ``(n, 3)`` relaxed penalty force on the target fed back to the body (two-way
            coupling; zero otherwise).
        coupling: constant part of the implicit coupling term (built on first use,
            :func:`penalty_coupling`).
        start_repaired: vertices the last warm start pulled towards the target because a
            face was turned over against the target's normals (:func:`admissible_start`).

    """

    options: ShellOptions
    topology: ShellTopology
    rest: np.ndarray
    embedding: Embedding
    clusters: Clusters
    energy: ShellEnergy
    solver: ShellNewtonSolver
    x: np.ndarray
    y: np.ndarray
    normals: np.ndarray
    edge_length: float
    gradient_scale: float = 0.0
    facts: dict[str, Any] = field(default_factory=dict)
    force: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    coupling: PenaltyCoupling | None = None
    start_repaired: int = 0

    def __post_init__(self) -> None:
        if self.force.shape != self.rest.shape:
            self.force = np.zeros_like(self.rest)

    @property
    def params(self) -> ShellParams:
        """The stiffnesses in use."""
        return self.energy.params


def build_shell(body: Body, options: ShellOptions, material: Material) -> Shell:
    """Surface -> subdivision -> rest shell, B, clusters and H, energy and solver (collective).

    Every rank builds the same shell (the surface is gathered identically on all ranks).
    """
    t0 = time.perf_counter()
    surface = mesh_surface(body.mesh)
    sub = subdivide(surface.vertices, surface.faces, options.subdivision)
    topology = ShellTopology.from_faces(sub.faces, sub.vertices.shape[0])
    emb = build_embedding(body.V, sub.vertices, options.embedding)
    rest = np.ascontiguousarray(sub.vertices)
    a = mean_edge_length(rest, topology)
    clusters = build_clusters(rest, sub.faces, cluster_options(options, material))
    params = shell_params(options, a)
    energy = ShellEnergy(topology, RestState.from_positions(topology, rest), params, clusters.H)
    solver = ShellNewtonSolver(energy, options.newton,  # type: ignore[arg-type]
                               hierarchy=ShellHierarchy(sub))
    facts = {"vertices": int(rest.shape[0]), "faces": int(sub.faces.shape[0]),
             "coarse_surface_vertices": int(surface.vertices.shape[0]),
             "mean_edge_length": a, "k_L": params.k_L, "k_A": params.k_A,
             "k_B": params.k_B, "k_P": params.k_P,
             "clusters": dataclasses.asdict(clusters.report),
             "embedding": dataclasses.asdict(emb.report),
             "setup_time": time.perf_counter() - t0}
    return Shell(options, topology, rest, emb, clusters, energy, solver, rest.copy(),
                 rest.copy(), vertex_normals(rest, sub.faces), a, facts=facts)


# --------------------------------------------------------------------------------------------
# Per frame


def target(shell: Shell, body: Body) -> np.ndarray:
    """``y = X_T + B u_q`` on every rank (collective)."""
    return shell.rest + apply_to_function(shell.embedding, body.u)


def imperfection(shell: Shell, frame: int) -> np.ndarray:
    """Deterministic perturbation ``eta_k`` of frame ``frame`` along the rest normals (n, 3)."""
    amp = shell.options.imperfection * shell.edge_length
    if amp == 0.0:
        return np.zeros_like(shell.x)
    rng = np.random.default_rng(frame)
    return amp * rng.standard_normal((shell.x.shape[0], 1)) * shell.normals


def _minimize(shell: Shell, x0: np.ndarray) -> tuple[np.ndarray, ShellSolveReport]:
    """Set the tolerance scale and minimise; ShellSolveError becomes a plain SolverError."""
    if shell.options.newton.gradient_scale == 0.0:
        ev = shell.energy.evaluate(x0, order=1)
        g0 = float(np.linalg.norm(np.asarray(ev.grad)))
        shell.gradient_scale = max(shell.gradient_scale, g0)
        shell.solver.options = dataclasses.replace(shell.options.newton,
                                                   gradient_scale=shell.gradient_scale or 1.0)
    try:
        return shell.solver.minimize(x0)
    except ShellSolveError as exc:
        raise SolverError(f"shell solve failed: {exc}") from None


START_HALVINGS: int = 40
"""Halvings of a turned-over face's offsets in :func:`admissible_start` before they are zeroed."""


def _turned_over(energy: ShellEnergy, x: np.ndarray) -> np.ndarray:
    """Faces (indices into the topology) whose flip barrier is +inf at ``x`` (s <= 0)."""
    ev = energy.evaluate(x, order=0)
    vals = ev.elements.get("flip_barrier")
    if np.isfinite(ev.value) or vals is None:
        return np.zeros(0, dtype=np.int64)
    return energy.flip_faces[~np.isfinite(vals)]


def admissible_start(energy: ShellEnergy, x0: np.ndarray, anchor: np.ndarray
                     ) -> tuple[np.ndarray, int]:
    """Return a warm start with a finite flip barrier and the number of vertices it moved.

    The warm start ``x_prev + (y - y_prev)`` carries the previous offset from the target onto
    the new target ``y``, but the barrier's reference normals are the face normals of ``y``
    (:meth:`models.shell.energy.ShellEnergy.set_target`): a face that ended the previous
    solve close to the barrier (s ~ 0.01, a wrinkle fold standing at ~90 degrees to its
    target face) is turned over against the new normals (s <= 0, W = +inf) when the target
    rotates under it, e.g. when two-way coupling moves the body. Measured on
    scenes/default.toml two-way implicit, frame 2: min s = 0.0104 after the first shell
    solve, -0.055 at the next iteration's warm start.

    Repair: for each face whose barrier is +inf, the offsets ``x0 - anchor`` of its three
    vertices are halved, repeated until no face is turned over (after
    :data:`START_HALVINGS` halvings they are set to 0). The anchor (the target plus the
    imperfection) has ``s > 0`` on every face whose target face is not degenerate, so only
    the vertices around the turned-over faces move and the wrinkles elsewhere are kept. A
    start that is admissible is returned unchanged (the same array: bitwise the old warm
    start, so one-way runs that never hit this are unchanged).

    Raises:
        SolverError: a face is turned over even at the anchor (degenerate target face).

    """
    bad = _turned_over(energy, x0)
    if bad.size == 0:
        return x0, 0
    x = np.array(x0, dtype=np.float64, copy=True)
    faces = energy.topology.faces
    for halving in range(START_HALVINGS + 1):
        verts = np.unique(faces[bad])
        factor = 0.5 if halving < START_HALVINGS else 0.0
        x[verts] = anchor[verts] + factor * (x[verts] - anchor[verts])
        bad = _turned_over(energy, x)
        if bad.size == 0:
            return x, int(np.any(x != x0, axis=1).sum())
    raise SolverError(f"shell warm start: face {int(bad[0])} {faces[bad[0]].tolist()} is turned "
                      f"over against its target normal even at the target (degenerate target "
                      f"face?)")


def solve_shell(shell: Shell, y: np.ndarray, frame: int, comm: MPI.Comm,
                perturb: bool = True) -> ShellSolveReport:
    """Move the target to ``y``, warm-start, minimise, take rank 0's x (collective).

    Every rank solves the same problem redundantly (serial solvers on ``COMM_SELF``; a
    rank-0-only solve no longer deadlocks since the PETSc log is begun at import,
    :func:`models.backend.begin_petsc_log`, but would leave the other ranks idle), then
    rank 0's result is broadcast so all ranks hold bitwise the same shell. ``perturb =
    False`` leaves out the imperfection (repeated solves of one frame in the coupling
    iteration). A warm start with a face turned over against the new target's normals is
    repaired first (:func:`admissible_start`; ``shell.start_repaired`` counts the vertices
    moved).
    """
    eta = imperfection(shell, frame) if perturb else 0.0
    x0 = shell.x + (y - shell.y) + eta
    shell.energy.set_target(y)
    x0, shell.start_repaired = admissible_start(shell.energy, x0, y + eta)
    x, report = _minimize(shell, x0)
    shell.x, shell.y = np.asarray(comm.bcast(x, root=0)), y
    return report


def deviation(shell: Shell) -> tuple[float, float]:
    """Return ``(max |x - y|, max |(x - y) . n_y|)``: total and normal distance from the target.

    ``n_y`` are the unit vertex normals of the target surface; the normal part is the wrinkle
    amplitude (tangential sliding inside the null space of H is not a wrinkle).
    """
    d = shell.x - shell.y
    normal = np.einsum("ij,ij->i", d, vertex_normals(shell.y, shell.topology.faces))
    return float(np.linalg.norm(d, axis=1).max()), float(np.abs(normal).max())


def shell_record(shell: Shell, report: ShellSolveReport) -> StageRecord:
    """Return the frame's shell numbers for the summary (rank-independent)."""
    ev = shell.energy.evaluate(shell.x, order=0)
    total, amplitude = deviation(shell)
    return {"shell_iterations": report.iterations, "shell_converged": report.converged,
            "shell_factorizations": report.factorizations,
            "shell_shifted_iterations": report.shifted_iterations,
            "shell_energy": ev.value, "shell_terms": dict(ev.terms),
            "shell_grad_norm": report.grad_norm, "shell_tolerance": report.tolerance,
            "shell_start_repaired": shell.start_repaired, "wrinkle_amplitude": amplitude,
            "wrinkle_amplitude_rel": amplitude / shell.edge_length,
            "max_distance_to_target": total,
            "shell_time_evaluate": report.time_evaluate,
            "shell_time_factorize": report.time_factorize,
            "shell_time_solve": report.time_solve, "shell_time_total": report.time_total}


STATE_ARRAYS: tuple[str, ...] = ("positions", "target", "gradient_scale", "force")
"""Checkpoint arrays of the shell: x, y, the tolerance reference and the fed-back force."""


def shell_arrays(shell: Shell) -> dict[str, np.ndarray]:
    """Return the shell state a resumed run needs to take the same steps (checkpoint arrays).

    The warm start ``x_0 = x + (y_new - y) + eta_k`` needs ``x`` and the previous target
    ``y``; the relative Newton tolerance needs the reference ``gradient_scale``; two-way
    coupling needs the relaxed force ``force`` (the body's load).
    """
    return {"positions": shell.x, "target": shell.y,
            "gradient_scale": np.array([shell.gradient_scale]), "force": shell.force}


def restore_shell(shell: Shell, arrays: Mapping[str, np.ndarray]) -> None:
    """Set the shell state from :func:`shell_arrays` of a checkpoint.

    Raises:
        InputError: an array is missing or has another shape (another shell).

    """
    for name in STATE_ARRAYS:
        expected = (1,) if name == "gradient_scale" else shell.rest.shape
        if name not in arrays or np.shape(arrays[name]) != expected:
            raise InputError(f"checkpoint: shell array {name!r} is missing or not of shape "
                             f"{expected} (another [shell] table?)")
    shell.x, shell.y = np.array(arrays["positions"]), np.array(arrays["target"])
    shell.force = np.array(arrays["force"])
    shell.gradient_scale = float(arrays["gradient_scale"][0])


def shell_frame(shell: Shell, t: float) -> ShellFrame:
    """Return the output fields of the current state."""
    return ShellFrame(t, shell.x - shell.rest, shell.energy.bending_density(shell.x))


# --------------------------------------------------------------------------------------------
# Stages


Writer = Callable[[int, float], None]


def make_writer(shell: Shell, out: Path, comm: MPI.Comm, writes: Callable[[int], bool],
                resume_after: float | None = None, atomic: bool = True) -> Writer:
    """Create ``shell.xdmf`` with the rest state (t = 0); return ``write(frame, t)``.

    With ``resume_after`` (time [s] of the restored state) the existing series is continued
    instead, without its steps after that time (collective: errors are raised on all ranks).
    """
    if not shell.options.xdmf:
        return lambda frame, t: None
    path, faces, cid = out / SHELL_XDMF_NAME, shell.topology.faces, shell.clusters.partition
    series = on_root(comm, lambda: ShellSeries(path, shell.rest, faces, cid, resume_after,
                                               atomic))
    if series is not None and resume_after is None:
        series.write(shell_frame(shell, 0.0))

    def write(frame: int, t: float) -> None:
        if series is not None and writes(frame):
            series.write(shell_frame(shell, t))

    return write


def one_way_stage(shell: Shell, body: Body, write: Writer) -> Callable[[int], StageRecord]:
    """Stage run after the body stage: target from the body, shell solve, output."""

    def stage(frame: int) -> StageRecord:
        report = solve_shell(shell, target(shell, body), frame, body.mesh.comm)
        write(frame, body.t)
        return shell_record(shell, report)

    return stage


def _max_abs(comm: MPI.Comm, a: np.ndarray) -> float:
    """Global max |a| over the ranks' owned + ghost values."""
    return float(comm.allreduce(float(np.abs(a).max(initial=0.0)), op=MPI.MAX))


def _relative_change(comm: MPI.Comm, new: np.ndarray, old: np.ndarray) -> float:
    """Coupling change ``max|new - old| / max|new|`` over all ranks."""
    return _max_abs(comm, new - old) / max(_max_abs(comm, new), 1e-300)


def apply_force(shell: Shell, body: Body) -> None:
    """Make the shell's relaxed force ``shell.force`` the body's nodal load ``B^T f``."""
    body.set_nodal_load(body_force_function(shell.embedding, shell.force, body.V))


def feed_back(shell: Shell, body: Body) -> None:
    """Relax the penalty force of the current shell into the body's nodal load ``B^T f``."""
    omega = shell.options.coupling.relaxation
    op = shell.energy.penalty_operator  # built once (None when k_P = 0: then H, zero force)
    f = penalty_force(op if op is not None else shell.clusters.H, shell.params.k_P, shell.x,
                      shell.y)
    shell.force = (1.0 - omega) * shell.force + omega * f
    apply_force(shell, body)


def coupling_record(shell: Shell, iterations: int, change: float, rtol: float,
                    force_body: list[float]) -> StageRecord:
    """Two-way coupling numbers: iterations, last relative change, converged, total forces.

    ``coupling_converged`` is False when the frame stopped at ``max_iterations`` with the
    change above ``rtol`` (the progress line then says so: the frame is kept, unconverged).
    """
    return {"coupling_iterations": iterations, "coupling_change": change,
            "coupling_converged": bool(change <= rtol),
            "coupling_force_shell": shell.force.sum(axis=0).tolist(),
            "coupling_force_body": force_body}


def two_way_stage(shell: Shell, body: Body, steps: int,
                  body_stage: Callable[[int], Mapping[str, Any]],
                  write: Writer) -> Callable[[int], StageRecord]:
    """Stage replacing body + shell: fixed point of body step <-> shell solve per frame.

    Body steps with the current load, shell solve; then repeatedly: feed the penalty force
    back (``B^T f``), redo the frame's body steps from the saved state, re-solve the shell,
    until ``max|u_k - u_{k-1}| <= rtol max|u_k|`` or ``max_iterations``.
    """
    opts, comm = shell.options.coupling, body.mesh.comm

    def stage(frame: int) -> StageRecord:
        saved, x_start, y_start = body.snapshot(), shell.x.copy(), shell.y.copy()
        record = dict(body_stage(frame))
        report = solve_shell(shell, target(shell, body), frame, comm)
        change, k, repaired = float("inf"), 0, shell.start_repaired
        for k in range(1, opts.max_iterations + 1):  # noqa: B007  (k is reported)
            u_old = body.u.x.array.copy()
            feed_back(shell, body)
            body.restore(saved)
            shell.x, shell.y = x_start.copy(), y_start.copy()
            record = dict(body_stage(frame))
            change = _relative_change(comm, body.u.x.array, u_old)
            report = solve_shell(shell, target(shell, body), frame, comm)
            repaired += shell.start_repaired
            if change <= opts.rtol:
                break
        write(frame, body.t)
        return {**record, **shell_record(shell, report), "shell_start_repaired": repaired,
                **coupling_record(shell, k, change, opts.rtol, body.applied_load().tolist())}

    return stage


def penalty_coupling(shell: Shell, body: Body) -> PenaltyCoupling:
    """Return the shell's :class:`models.coupling.PenaltyCoupling` (assembled on first use)."""
    if shell.coupling is None:
        shell.coupling = PenaltyCoupling.build(shell.embedding, shell.clusters.H,
                                               shell.params.k_P, body.V)
    return shell.coupling


def coupled_force(shell: Shell, body: Body) -> list[float]:
    """Total force [N] of the implicit penalty term on the body, ``-sum_j (K u - c)_j``."""
    term = penalty_coupling(shell, body).term(shell.x - shell.rest)
    g = term.gradient(body.u.x.petsc_vec)
    local = g.array.reshape(-1, 3).sum(axis=0)
    for obj in (g, term.c):
        obj.destroy()
    return [-float(v) for v in body.mesh.comm.allreduce(local, op=MPI.SUM)]


@dataclass
class Aitken:
    """Aitken's dynamic relaxation of a fixed-point iteration ``x -> G(x)``.

    Irons & Tuck 1969; Kuettler & Wall 2008 for partitioned coupling.
    With the residual ``r_k = G(x_k) - x_k`` the next iterate is ``x_k + omega_k r_k`` and

        omega_k = -omega_{k-1} r_{k-1} . (r_k - r_{k-1}) / |r_k - r_{k-1}|^2,

    (``omega_0 = 1``), the secant estimate of ``1 / (1 - lambda)`` for the dominant
    eigenvalue ``lambda`` of the iteration: a slow linear contraction becomes fast.

    Attributes:
        omega: current relaxation factor.
        residual: previous residual ``r_{k-1}`` (``None`` before the first step).

    """

    omega: float = 1.0
    residual: np.ndarray | None = None

    def relax(self, x: np.ndarray, gx: np.ndarray) -> np.ndarray:
        """Return the relaxed next iterate from ``x_k`` and ``G(x_k)``."""
        r = gx - x
        if self.residual is not None:
            dr = r - self.residual
            denom = float(np.sum(dr * dr))
            if denom > 0.0:
                self.omega = -self.omega * float(np.sum(self.residual * dr)) / denom
        self.residual = r
        return x + self.omega * r


@dataclass
class Anderson:
    """Anderson acceleration of a fixed-point iteration ``x -> G(x)`` (IQN-ILS).

    Anderson 1965; Degroote, Bathe & Vierendeels 2009 (interface quasi-Newton with an
    inverse Jacobian from a least-squares model) for partitioned coupling. With the
    residuals ``r_i = G(x_i) - x_i`` and the differences ``dR_i = r_{i+1} - r_i``,
    ``dG_i = G(x_{i+1}) - G(x_i)`` of the last ``memory`` iterations,

        gamma = argmin |r_k - dR gamma|,     x_{k+1} = G(x_k) - dG gamma,

    (the first step is the plain ``x_1 = G(x_0)``): the secants of all ``memory`` slow modes
    at once, where :class:`Aitken` fits one scalar factor to all of them.

    Attributes:
        memory: number of difference columns kept, >= 1.
        rcond: relative singular value below which the least-squares problem drops a
            direction (``numpy.linalg.lstsq``).
        residuals: previous residuals ``r_i`` (oldest first, at most ``memory + 1``).
        images: previous images ``G(x_i)``, aligned with ``residuals``.
        gamma: coefficients of the last step (diagnostics).

    """

    memory: int = 8
    rcond: float = 1e-10
    residuals: list[np.ndarray] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)
    gamma: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def relax(self, x: np.ndarray, gx: np.ndarray) -> np.ndarray:
        """Return the next iterate from ``x_k`` and ``G(x_k)``."""
        r = (gx - x).reshape(-1)
        g = np.asarray(gx).reshape(-1)
        self.residuals.append(r)
        self.images.append(g)
        del self.residuals[:-(self.memory + 1)], self.images[:-(self.memory + 1)]
        if len(self.residuals) < 2:
            self.gamma = np.zeros(0)
            return np.array(gx, dtype=np.float64, copy=True)
        dR = np.diff(np.stack(self.residuals, axis=1), axis=1)
        dG = np.diff(np.stack(self.images, axis=1), axis=1)
        self.gamma = np.linalg.lstsq(dR, r, rcond=self.rcond)[0]
        return (g - dG @ self.gamma).reshape(np.shape(gx))


def accelerator(options: CouplingOptions) -> Aitken | Anderson | None:
    """Return the accelerator of ``options.acceleration`` (``None``: plain alternation)."""
    if options.acceleration == "aitken":
        return Aitken()
    if options.acceleration == "anderson":
        return Anderson(memory=options.memory)
    return None


def implicit_stage(shell: Shell, body: Body, body_stage: Callable[[int], Mapping[str, Any]],
                   write: Writer) -> Callable[[int], StageRecord]:
    """Stage replacing body + shell: alternate minimisation of body and shell energies.

    Iteration ``k`` redoes the frame's body steps from the saved state with the penalty as an
    implicit quadratic term ``1/2 u^T K u - c_k^T u`` (its constant matrix built once,
    :func:`penalty_coupling`; :func:`models.coupling.penalty_term`), then solves the shell
    for the new target. Without acceleration ``c_k = M (x_{k-1} - X_T)`` of the last shell:
    block Gauss-Seidel on the total energy ``Pi(u) + W(x, y(u))``, each half-step a
    minimisation, so the total energy decreases monotonically. Ends when
    ``max|u_k - u_{k-1}| <= rtol max|u_k|`` or ``max_iterations``. The record's
    ``coupling_force_body`` is the term's total force on the body (equal to
    ``coupling_force_shell = sum_i f_i`` since the rows of B sum to 1).

    The alternation converges linearly and slowly, since the skin and the soft body are
    strongly coupled through the penalty: measured contraction per iteration ~0.95 on the
    1000x-skin bar of ``tests/test_followup_implicit_coupling.py``, ~0.90 and ~0.977 on
    frames 1 and 2 of scenes/default.toml (2 frames, 1 subdivision level). ``coupling.
    acceleration`` therefore extrapolates the body load ``c`` (all the body sees of the
    shell, ``3 n_b`` numbers; the shell keeps its own solved state as the next warm start)
    with :class:`Anderson` (default) or :class:`Aitken`: measured on that default-scene run,
    Anderson reaches ``rtol = 1e-6`` in 36 and 60 iterations (38 and 61 with the presets'
    x5 / 2 shift schedule); Aitken on the shell iterate
    (the previous scheme) stalled (2.9e-4 after 25 iterations on frame 1, factors jumping
    between 1 and 8.5), as did Anderson on the shell iterate (2.3e-5 after 30 iterations:
    the secants then also fit the shell's sliding and wrinkle modes that the body does not
    see). Not the cause (measured):
    the shell tolerance (shell ``rtol`` 1e-10 instead of 1e-6 gives the same iterates to 3
    digits) and wrinkle flips (none); frame 2 has isolated shell re-arrangements (a solve of
    17-38 Newton iterations moving a vertex by 2-6 mm against ~0.2 mm otherwise) that cost
    Anderson its secant history.
    """
    opts, comm = shell.options.coupling, body.mesh.comm

    def stage(frame: int) -> StageRecord:
        saved, change, k = body.snapshot(), float("inf"), 0
        coupling = penalty_coupling(shell, body)
        record: dict[str, Any] = {}
        report = None
        accel = accelerator(opts)
        repaired = 0
        load = coupling.load(shell.x - shell.rest)
        for k in range(1, opts.max_iterations + 1):  # noqa: B007  (k is reported)
            u_old = body.u.x.array.copy()
            body.set_quadratic_energy(coupling.load_term(load,
                                                         coupling.energy(shell.x - shell.rest)))
            body.restore(saved)
            record = dict(body_stage(frame))
            change = _relative_change(comm, body.u.x.array, u_old)
            report = solve_shell(shell, target(shell, body), frame, comm, perturb=k == 1)
            repaired += shell.start_repaired
            if change <= opts.rtol:
                break
            image = coupling.load(shell.x - shell.rest)
            load = image if accel is None else accel.relax(load, image)
        assert report is not None  # max_iterations >= 1
        shell.force = penalty_force(coupling.op, shell.params.k_P, shell.x, shell.y)
        write(frame, body.t)
        return {**record, **shell_record(shell, report), "shell_start_repaired": repaired,
                **coupling_record(shell, k, change, opts.rtol, coupled_force(shell, body))}

    return stage


__all__ = ["Aitken", "Anderson", "Shell", "ShellOptions", "SkinOptions", "accelerator",
           "apply_force", "build_shell", "make_writer",
           "one_way_stage", "restore_shell", "shell_arrays", "shell_record", "solve_shell",
           "target", "two_way_stage", "implicit_stage"]
