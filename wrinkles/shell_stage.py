"""The embedded shell's per-frame solve (Algorithm 1 of the draft) and its one-way stage.

Per frame, after the body step:

    y   = B (X_q + u_q) = X_T + B u_q                     (target; B reproduces X_q exactly)
    x_0 = y + R_i (x_prev - y_prev)_i + eta_k            (warm start carried with the body)
    x   = argmin W                                        (Newton on every rank, rank 0's x kept)

``R_i`` is the rotation of the target around vertex i since the previous frame
(:func:`carried_start`). ``eta_k`` is a tiny deterministic imperfection along the rest vertex
normals (``imperfection`` times the mean rest edge length, seeded by the frame number): a flat
face compressed exactly in its plane is a stationary point of W, so without it no wrinkle can
form. The shell is solved by :attr:`Shell.solver`: on one rank the serial Newton, on more the
Newton split over the ranks (each evaluates its own vertices' stencils and holds their rows of
the distributed Newton system; every rank ends with the same x). The set-up is
:mod:`wrinkles.shell_setup`, two-way coupling :mod:`wrinkles.two_way`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from meshes.errors import InputError, SolverError
from models.backend import MPI
from models.embedding.embedding import apply_to_function
from models.shell.energy import ShellEnergy
from models.shell.local_rotation import local_rotations
from models.shell.rest import vertex_normals
from solvers.body import Body
from solvers.decomposition.split_newton import SplitNewtonSolver
from solvers.shell_newton import (
    ShellNewtonOptions,
    ShellNewtonSolver,
    ShellSolveError,
    ShellSolveReport,
)
from solvers.solver_choice import wrinkled_start
from wrinkles.shell_output import Writer
from wrinkles.shell_setup import Shell

StageRecord = dict[str, Any]


def target(shell: Shell, body: Body) -> np.ndarray:
    """``y = X_T + B u_q`` on every rank (collective)."""
    return shell.rest + apply_to_function(shell.embedding, body.u)


def imperfection(shell: Shell, frame: int) -> np.ndarray:
    """Deterministic perturbation ``eta_k`` of frame ``frame`` along the rest normals (n, 3).

    ``imperfection x edge_length x xi_i n_i`` with ``xi_i`` standard normal, drawn from
    NumPy's ``SeedSequence(frame)`` for ``imperfection_seed`` 0 and ``SeedSequence([frame,
    seed])`` otherwise: the same on every rank and in a resumed run.
    """
    amp = shell.options.imperfection * shell.edge_length
    if amp == 0.0:
        return np.zeros_like(shell.x)
    seed = shell.options.imperfection_seed
    rng = np.random.default_rng(frame if seed == 0 else [frame, seed])
    return amp * rng.standard_normal((shell.x.shape[0], 1)) * shell.normals


def scale_tolerance(shell: Shell, solver: ShellNewtonSolver | SplitNewtonSolver, x0: np.ndarray,
                    options: ShellNewtonOptions) -> None:
    """Give ``solver`` the options with the largest initial gradient so far as reference.

    ``shell.gradient_scale`` (checkpointed) becomes ``max(itself, ||grad E(x0)||)`` and the
    relative tolerance of the coming solve refers to it, so a warm start that is already good
    is not driven to an over-tight tolerance. Nothing changes when ``options`` fix a scale.
    """
    if options.gradient_scale != 0.0:
        return
    g0 = float(np.linalg.norm(np.asarray(solver.energy.evaluate(x0, order=1).grad)))
    shell.gradient_scale = max(shell.gradient_scale, g0)
    solver.options = dataclasses.replace(options, gradient_scale=shell.gradient_scale or 1.0)


def minimize_from_state(shell: Shell, solver: ShellNewtonSolver | SplitNewtonSolver,
                        x0: np.ndarray, options: ShellNewtonOptions
                        ) -> tuple[np.ndarray, ShellSolveReport]:
    """Minimise from ``x0`` with the shell's solver state: tolerance reference, shift memory.

    :func:`scale_tolerance`, then the solver's shift memory is set from ``shell.shifts`` and,
    however the solve ends, written back: the checkpoint carries it, so a resumed run takes
    the steps of the run it continues (bit for bit on the direct path of a static scene; on
    the multigrid path the coarser levels keep the Chebyshev bounds of their KSP's first
    set-up, a resumed run's first frame, and a dynamic scene's frame starts from the
    previous frame's factorisation (:func:`solvers.solver_choice.choose_factor_reuse`),
    which a checkpoint does not hold, so its resumed first frame factorises afresh: these
    reach the same minimisers to the solver's tolerance).

    Raises:
        ShellSolveError: as ``solver.minimize``.

    """
    scale_tolerance(shell, solver, x0, options)
    solver.shift_state = shell.shifts
    try:
        return solver.minimize(x0)
    finally:
        shell.shifts = solver.shift_state


def _minimize(shell: Shell, x0: np.ndarray) -> tuple[np.ndarray, ShellSolveReport]:
    """Minimise from the shell's state; ShellSolveError becomes a plain SolverError.

    The multigrid's phase space (where the shell has one) serves the solve from its start when
    the warm start lies wrinkled off its target, else from its first negative curvature
    (:func:`solvers.solver_choice.wrinkled_start`).
    """
    offset = float(np.linalg.norm(x0 - shell.energy.target, axis=1).max())
    shell.solver.use_phase_space(wrinkled_start(offset, shell.edge_length))
    try:
        return minimize_from_state(shell, shell.solver, x0, shell.options.internals.newton)
    except ShellSolveError as exc:
        raise SolverError(f"shell solve failed: {exc}") from None


START_HALVINGS: int = 40
"""Halvings of a blocked stencil's offsets in :func:`admissible_start` before they are zeroed."""


def admissible_start(energy: ShellEnergy, x0: np.ndarray, anchor: np.ndarray
                     ) -> tuple[np.ndarray, int]:
    """Return a warm start with finite barriers and the number of vertices it moved.

    The warm start (:func:`carried_start`) carries the previous offset from the target onto
    the new target ``y``, but the flip barrier's reference normals are the face normals of
    ``y`` (:meth:`models.shell.energy.ShellEnergy.set_target`): a face that ended the previous
    solve close to the barrier (s ~ 0.01, a wrinkle fold standing at ~90 degrees to its
    target face) can be turned over against the new normals (s <= 0, W = +inf) where the
    target deforms under it, e.g. when two-way coupling moves the body
    (docs/notes/two-way-coupling.md);
    likewise a fold held shut by the fold contact can be carried through itself.

    Repair: the offsets ``x0 - anchor`` of the vertices of every blocked stencil
    (:meth:`~models.shell.energy.ShellEnergy.blocked_vertices`) are halved, repeated until
    none is blocked (after :data:`START_HALVINGS` halvings they are set to 0). The anchor
    (the target plus the imperfection) has no turned-over face where the target is not
    degenerate, so only the vertices around them move and the wrinkles elsewhere are kept.
    A hinge can still be closed through itself at the anchor: its followed angle differs
    from the target's by more than pi (a fold carried through itself by an unconverged
    solve, then pulled back onto a target bent the other way); such hinges take the
    principal branch at the anchor
    (:meth:`~models.shell.energy.ShellEnergy.release_folds`). A start that is admissible is
    returned unchanged (the same array).

    Raises:
        SolverError: a face stays turned over even at the anchor (a degenerate target face).

    """
    verts = energy.blocked_vertices(x0)
    if verts.size == 0:
        return x0, 0
    x = np.array(x0, dtype=np.float64, copy=True)
    for halving in range(START_HALVINGS + 1):
        factor = 0.5 if halving < START_HALVINGS else 0.0
        x[verts] = anchor[verts] + factor * (x[verts] - anchor[verts])
        if halving == START_HALVINGS:
            energy.release_folds(x)  # folds still closed through themselves at the anchor
        verts = energy.blocked_vertices(x)
        if verts.size == 0:
            return x, int(np.any(x != x0, axis=1).sum())
    raise SolverError(f"shell warm start: vertex {int(verts[0])} stays on a face turned over "
                      f"even when pulled back onto the target (a degenerate target face)")


def settled(shell: Shell, x0: np.ndarray) -> bool:
    """Whether ``x0`` already meets the gradient tolerance of the shell's next solve.

    The tolerance is the one :func:`minimize_from_state` gives the solver, ``atol + rtol
    g_ref``, with ``g_ref`` the largest initial gradient so far (or the options' fixed
    scale); before the first solve there is no reference and nothing counts as settled.
    """
    options = shell.options.internals.newton
    scale = options.gradient_scale or shell.gradient_scale
    if scale == 0.0:
        return False
    grad = np.asarray(shell.energy.evaluate(x0, order=1).grad)
    return bool(np.linalg.norm(grad) <= options.atol + options.rtol * scale)


def carried_start(shell: Shell, y: np.ndarray) -> np.ndarray:
    """Return ``y + R_i (x_prev - y_prev)_i``: the wrinkles carried onto the new target.

    The offset of every vertex from the previous target is turned with the rotation of the
    target around it from ``y_prev`` to ``y``
    (:func:`models.shell.local_rotation.local_rotations`), so that a target that rotates
    (a bent or twisted body, a tumbling one) takes its wrinkles along instead of leaving
    them pointing the old way; a translated target gives ``x_prev + (y - y_prev)``.
    """
    rotations = local_rotations(shell.y, y, shell.topology.faces, shell.topology.edges)
    return y + np.einsum("nij,nj->ni", rotations, shell.x - shell.y)


def warm_start(shell: Shell, y: np.ndarray, frame: int, perturb: bool = True,
               unless_settled: bool = False) -> np.ndarray:
    """Move the target to ``y``; return the warm start :func:`carried_start` ``+ eta_k``.

    ``eta_k`` only when ``perturb``, and with ``unless_settled`` only when the carried start
    is not already a solution (:func:`settled`: the body moved the shell's target rigidly,
    or not at all): the Newton would spend its iterations removing the
    imperfection again. A start with a face turned over against the new target's normals
    is repaired (:func:`admissible_start`; ``shell.start_repaired`` counts the vertices
    moved). The hinge angles are followed to the start
    (:meth:`wrinkles.shell_setup.Shell.follow_hinges`).
    """
    x0 = carried_start(shell, y)
    shell.set_target(y)
    if perturb and unless_settled and settled(shell, x0):
        perturb = False
    eta = imperfection(shell, frame) if perturb else 0.0
    x0, shell.start_repaired = admissible_start(shell.energy, x0 + eta, y + eta)
    shell.follow_hinges(x0)
    return x0


def solve_shell(shell: Shell, y: np.ndarray, frame: int, comm: MPI.Comm,
                perturb: bool = True) -> ShellSolveReport:
    """Move the target to ``y``, warm-start, minimise, take rank 0's x (collective).

    The ranks solve together (:attr:`Shell.solver`, split over the ranks when there are
    several), then rank 0's result is broadcast so all ranks hold bitwise the same shell.
    ``perturb = False`` leaves out the imperfection (repeated solves of one frame in the
    coupling iteration); it is left out too where the warm start is already a solution
    (:func:`warm_start`), so a frame that only moves the shell rigidly takes no iteration.
    A warm start with a face turned over against the new target's normals is repaired
    first (:func:`admissible_start`; ``shell.start_repaired`` counts the vertices moved).
    """
    x, report = _minimize(shell, warm_start(shell, y, frame, perturb, unless_settled=True))
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
    """Return the frame's shell numbers for the summary (rank-independent).

    ``shell_self_intersections`` counts the face pairs passing through each other
    (:meth:`wrinkles.shell_setup.Shell.intersecting_faces`): the energy has no contact
    between faces that share no hinge, so a fold pressed onto its neighbours can.
    """
    ev = shell.energy.evaluate(shell.x, order=0)
    total, amplitude = deviation(shell)
    return {"shell_iterations": report.iterations, "shell_converged": report.converged,
            "shell_factorizations": report.factorizations,
            "shell_shifted_iterations": report.shifted_iterations,
            "shell_energy": ev.value, "shell_terms": dict(ev.terms),
            "shell_grad_norm": report.grad_norm, "shell_tolerance": report.tolerance,
            "shell_start_repaired": shell.start_repaired,
            "shell_phase_space": shell.solver.phase_space_in_use, "wrinkle_amplitude": amplitude,
            "wrinkle_amplitude_rel": amplitude / shell.edge_length,
            "max_distance_to_target": total,
            "shell_self_intersections": len(shell.intersecting_faces()),
            "shell_time_evaluate": report.time_evaluate,
            "shell_time_factorize": report.time_factorize,
            "shell_time_solve": report.time_solve, "shell_time_total": report.time_total}


STATE_ARRAYS: tuple[str, ...] = ("positions", "target", "gradient_scale", "force", "shifts",
                                 "hinge_branch")
"""Checkpoint arrays of the shell: x, y, the tolerance reference, the penalty force, the
Newton's shift memory and the hinges' reference angles (the last two absent from checkpoints
written before they existed: zeros, and none)."""


def shell_arrays(shell: Shell) -> dict[str, np.ndarray]:
    """Return the shell state a resumed run needs to take the same steps (checkpoint arrays).

    The warm start ``x_0 = y_new + R_i (x - y)_i + eta_k`` needs ``x`` and the previous
    target ``y``; the relative Newton tolerance needs the reference ``gradient_scale``; two-way
    coupling keeps the penalty force ``force`` (its share on pinned body nodes counts in the
    pins' reaction); the shifts of the next solve start from ``shifts``; its hinge angles
    are followed from ``hinge_branch`` (empty before the first solve: none).
    """
    branch = shell.energy.hinge_branch
    return {"positions": shell.x, "target": shell.y,
            "gradient_scale": np.array([shell.gradient_scale]), "force": shell.force,
            "shifts": np.array(shell.shifts),
            "hinge_branch": np.zeros(0) if branch is None else branch}


def restore_shell(shell: Shell, arrays: Mapping[str, np.ndarray]) -> None:
    """Set the shell state from :func:`shell_arrays` of a checkpoint.

    A checkpoint without ``shifts`` or ``hinge_branch`` (written before the shift memory or
    the hinge references existed) restores zeros and no references, the steps of the code
    that wrote it.

    Raises:
        InputError: an array is missing or has another shape (another shell).

    """
    arrays = {"shifts": np.zeros(2), "hinge_branch": np.zeros(0), **arrays}
    hinges = shell.energy.topology.hinges.shape[0]
    branch_shape = (0,) if np.size(arrays["hinge_branch"]) == 0 else (hinges,)
    for name in STATE_ARRAYS:
        expected = {"gradient_scale": (1,), "shifts": (2,),
                    "hinge_branch": branch_shape}.get(name, shell.rest.shape)
        if name not in arrays or np.shape(arrays[name]) != expected:
            raise InputError(f"checkpoint: shell array {name!r} is missing or not of shape "
                             f"{expected} (another [shell] table?)")
    shell.x, shell.y = np.array(arrays["positions"]), np.array(arrays["target"])
    shell.force = np.array(arrays["force"])
    shell.gradient_scale = float(arrays["gradient_scale"][0])
    shell.shifts = np.array(arrays["shifts"], dtype=np.float64)
    branch = np.array(arrays["hinge_branch"], dtype=np.float64)
    shell.energy.set_hinge_branch(branch if branch.size else None)


def check_resumed_target(shell: Shell, body: Body) -> None:
    """Raise InputError unless a restored target is this shell's ``X_T + B u_q`` (collective).

    The checkpoint holds the shell's vertex arrays, not how its vertices were made: a run
    written from another surface with as many vertices (another mesh file under the same
    name, or a code whose coarse surface differed, e.g. before cap slivers were flipped,
    :mod:`models.embedding.caps`) would otherwise resume with its positions on other
    vertices. Round-off is far below the bound, a thousandth of the mean edge.
    """
    gap = float(np.max(np.abs(shell.y - target(shell, body)), initial=0.0))
    if not gap <= 1e-3 * shell.edge_length:
        raise InputError(f"checkpoint: the shell's stored target lies up to {gap:.3g} off this "
                         f"shell's embedding of the body (the run was written from another "
                         f"surface: another mesh or code version); run it again with "
                         f"--overwrite")


def one_way_stage(shell: Shell, body: Body, write: Writer) -> Callable[[int], StageRecord]:
    """Stage run after the body stage: target from the body, shell solve, output."""

    def stage(frame: int) -> StageRecord:
        report = solve_shell(shell, target(shell, body), frame, body.mesh.comm)
        write(frame, body.t)
        return shell_record(shell, report)

    return stage


__all__ = ["StageRecord", "admissible_start", "carried_start", "deviation", "imperfection",
           "one_way_stage", "minimize_from_state", "restore_shell", "scale_tolerance",
           "shell_arrays", "settled", "shell_record", "solve_shell", "target", "warm_start"]
