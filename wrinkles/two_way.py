"""Two-way coupling of the shell with the body, as one stage replacing both per frame.

Remillard & Kry 2013 couple skin and body both ways: the cluster penalty ``k_P ||H (x - y(u))||^2``
acts on the body too. By default (``coupling.scheme = "monolithic"``) every body step is one
Newton solve of body and shell together (:class:`CoupledStep`, :mod:`solvers.monolithic`);
the fixed point (``"implicit"``, the reference) iterates body step and shell solve per frame
instead (:func:`solvers.coupling.coupled_frame`). The record
adds the coupling iterations, the last change (monolithic: the final relative gradient),
whether it converged, and the penalty's total force on shell and body (equal, since the rows
of B sum to 1).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from meshes.errors import SolverError
from models.backend import MPI
from models.coupling import PenaltyCoupling, body_force_function, penalty_force
from solvers.body import Body
from solvers.body_newton import EnergyNewton, NewtonResult
from solvers.coupling import coupled_frame
from solvers.decomposition.split_coupled import (
    SplitCoupledEnergy,
    SplitJointKrylov,
    split_joint_system,
)
from solvers.decomposition.split_newton import SplitNewtonSolver
from solvers.joint_krylov import JointKrylovSystem
from solvers.monolithic import JOINT_LINEAR, BodyUnknowns, CoupledEnergy
from solvers.multigrid import MultigridLinearSystem
from solvers.shell_newton import (
    ModifiedNewtonOptions,
    ShellNewtonSolver,
    ShellSolveError,
    ShellSolveReport,
)
from solvers.solver_choice import choose_joint_split
from wrinkles.shell_output import Writer
from wrinkles.shell_setup import Shell
from wrinkles.shell_stage import (
    StageRecord,
    minimize_from_state,
    shell_record,
    solve_shell,
    target,
    warm_start,
)


class CoupledStep:
    """The body's step solve as the monolithic solve of body and shell (collective).

    Installed by :meth:`solvers.body.Body.use_solve`, so the body's step control (pins,
    inertia, halvings, rigid balls) is unchanged. Per call: the shell's warm start moves with
    the body's guess (``x_prev + (y(u_0) - y_prev)``, the frame's imperfection on the first
    call of a frame, :func:`wrinkles.shell_stage.warm_start`), then the shell's Newton
    solver minimises :class:`solvers.monolithic.CoupledEnergy` over shell and body at once
    (the joint system factorised, :data:`solvers.monolithic.JOINT_LINEAR`, or by CG when the
    shell's own size chose multigrid, :mod:`solvers.joint_krylov`). Only a converged solve
    moves the shell; a failed one reports failure and the body halves its step. The gradient
    reference is the largest initial coupled gradient so far (``shell.gradient_scale``,
    checkpointed).
    """

    def __init__(self, shell: Shell, body: Body) -> None:
        self.shell, self.body = shell, body
        self.B = shell.embedding.global_matrix()
        self.options = dataclasses.replace(shell.options.internals.newton,
                                           linear_method="direct",
                                           augmented_linear=JOINT_LINEAR,
                                           modified=ModifiedNewtonOptions())
        self.solvers: dict[int, tuple[CoupledEnergy, ShellNewtonSolver]] = {}
        self.frame, self.perturb = 0, True
        self.reports: list[ShellSolveReport] = []
        self.joint_system = "whole"
        """How the ranks hold the joint system: "whole" on every rank, or "split"."""

    def start_frame(self, frame: int) -> None:
        """Begin frame ``frame``: its first solve adds the imperfection."""
        self.frame, self.perturb, self.reports = frame, True, []

    def _solver(self, problem: EnergyNewton) -> tuple[CoupledEnergy, ShellNewtonSolver]:
        """Return the coupled energy and its solver for a step problem (static or dynamic)."""
        key = id(problem)
        if key not in self.solvers:
            energy = CoupledEnergy(self.shell.energy, self.shell.rest, self.B,
                                   BodyUnknowns(problem))
            split = self._split(energy)
            if split is not None:
                self.joint_system = "split"
                self.solvers[key] = (energy, ShellNewtonSolver(split[0], self.options,
                                                               krylov=split[1]))
            else:
                self.solvers[key] = (energy, ShellNewtonSolver(energy, self.options,
                                                               krylov=self._krylov(energy)))
        return self.solvers[key]

    def _split(self, energy: CoupledEnergy) -> tuple[SplitCoupledEnergy, SplitJointKrylov] | None:
        """Return the joint energy and CG with the shell split over the ranks, or None.

        Where the shell's own solver is split over the ranks
        (:func:`wrinkles.shell_setup.shell_solver`) and :func:`solvers.solver_choice.
        choose_joint_split` says so (multigrid-CG, the shell's size): each rank then
        evaluates and holds its own vertices' rows of the joint system
        (:mod:`solvers.decomposition.split_coupled`). Otherwise every rank solves the whole
        joint system.
        """
        solver, hierarchy = self.shell.solver, self.shell.hierarchy
        newton = self.shell.options.internals.newton
        if (not isinstance(solver, SplitNewtonSolver) or hierarchy is None
                or energy.factor is None or not choose_joint_split(
                    solver.comm.size, energy.n, newton.linear_method)):
            return None
        return split_joint_system(solver, energy, hierarchy.prolongations(), newton.multigrid)

    def _krylov(self, energy: CoupledEnergy) -> JointKrylovSystem | None:
        """Return the joint CG when the shell is solved by multigrid-CG, else None (direct).

        The shell's own choice by size (:mod:`solvers.solver_choice`) decides for the joint
        system too: its cost is the shell's V-cycles plus the coarse body's factorised block.
        The shell solver's own multigrid serves as the shell block (the monolithic step does
        not run that solver; it is built without the phase space for it), or a new one
        where a scene asked for the phase space.
        """
        newton, hierarchy = self.shell.options.internals.newton, self.shell.hierarchy
        if newton.linear_method != "multigrid" or hierarchy is None or energy.factor is None:
            return None
        own = getattr(self.shell.solver, "krylov", None)
        shell_mg = (own if isinstance(own, MultigridLinearSystem) and own.phase is None else
                    MultigridLinearSystem(hierarchy.prolongations(),
                                          dataclasses.replace(newton.multigrid,
                                                              phase_space=False)))
        return JointKrylovSystem(shell_mg, energy.shell.penalty_factor, energy.body_factor)

    def _start(self, energy: CoupledEnergy) -> np.ndarray:
        """Return the warm start ``z_0 = (x_0, u_0)``, ``u_0`` the body's guess."""
        u0 = energy.body.get().reshape(-1, 3)
        x0 = warm_start(self.shell, energy.target(u0), self.frame, self.perturb)
        return np.vstack([x0, u0])

    def __call__(self, problem: EnergyNewton) -> NewtonResult:
        """Solve the step coupled; leave ``u`` (and the shell) at the solution on success.

        A guess with ``det F <= 0`` somewhere (a pin moved across its elements) or a shell
        start that cannot be made admissible is a failed solve, like the body's own: the body
        halves its step.
        """
        energy, solver = self._solver(problem)
        min_det = problem.min_det_f()
        if not min_det > 0.0:
            return NewtonResult(False, 0, 0, math.nan, math.inf, min_det)
        try:
            z0 = self._start(energy)
        except SolverError:
            return NewtonResult(False, 0, 0, math.nan, math.inf, min_det)
        try:
            z, report = minimize_from_state(self.shell, solver, z0, self.options)
        except ShellSolveError as exc:
            z, report = None, exc.report
        self.reports.append(report)
        if z is None or not report.converged:  # the body restores its state and halves
            return NewtonResult(False, -1, report.iterations, report.grad_norm, math.inf,
                                problem.min_det_f())
        x, u = energy.split(self.body.mesh.comm.bcast(z, root=0))
        energy.body.set(u.reshape(-1))
        self.shell.x, self.shell.y = np.array(x), energy.target(u)
        # the barrier's reference normals stay the solve's: the frame's record evaluates W
        # where the solve left it (the next warm start takes the new target's normals)
        self.shell.energy.set_target(self.shell.y, normals=False)
        self.set_force()
        self.perturb = False
        return NewtonResult(True, 1, report.iterations, report.grad_norm, report.energy,
                            problem.min_det_f())

    def set_force(self) -> None:
        """Set the current shell's penalty force ``f`` as ``shell.force`` and the body's force.

        The body gets ``B^T f`` as its interface force (the pins' share of it counts in their
        reaction, :meth:`solvers.body.Body.set_interface_force`).
        """
        shell = self.shell
        op = shell.energy.penalty_operator
        shell.force = (penalty_force(op, shell.params.k_P, shell.x, shell.y) if op is not None
                       else np.zeros_like(shell.x))
        self.body.set_interface_force(body_force_function(shell.embedding, shell.force,
                                                          self.body.V))

    def frame_report(self) -> ShellSolveReport:
        """Return the frame's solves as one report: summed iterations and times, last state."""
        last = self.reports[-1]
        return dataclasses.replace(
            last, iterations=sum(r.iterations for r in self.reports),
            history=tuple(h for r in self.reports for h in r.history),
            **{name: sum(getattr(r, name) for r in self.reports)
               for name in ("time_evaluate", "time_line_search", "time_factorize",
                            "time_analysis", "time_solve", "time_total")})


def coupling_record(shell: Shell, iterations: int, change: float, converged: bool,
                    force_body: list[float]) -> StageRecord:
    """Two-way coupling numbers: iterations, last relative change, converged, total forces.

    ``coupling_converged`` is False when a fixed-point frame stopped at ``max_iterations``
    with the change above ``rtol`` (the progress line then says so: the frame is kept,
    unconverged). For the monolithic solve ``iterations`` are its Newton iterations and
    ``change`` its final gradient norm relative to the reference.
    """
    return {"coupling_iterations": iterations, "coupling_change": change,
            "coupling_converged": bool(converged),
            "coupling_force_shell": shell.force.sum(axis=0).tolist(),
            "coupling_force_body": force_body}


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


def two_way_stage(shell: Shell, body: Body, body_stage: Callable[[int], Mapping[str, Any]],
                  write: Writer) -> Callable[[int], StageRecord]:
    """Return the stage of the scene's two-way scheme (implicit: :func:`coupled_frame`)."""
    options, comm = shell.options.internals.coupling, body.mesh.comm
    if options.scheme == "monolithic":
        return monolithic_stage(shell, body, body_stage, write)

    def stage(frame: int) -> StageRecord:
        coupling = penalty_coupling(shell, body)
        repaired = 0

        def solve(first: bool) -> Any:
            nonlocal repaired
            report = solve_shell(shell, target(shell, body), frame, comm, perturb=first)
            repaired += shell.start_repaired
            return report

        result = coupled_frame(body, coupling, options, lambda: shell.x - shell.rest,
                               lambda: body_stage(frame), solve)
        shell.force = penalty_force(coupling.op, shell.params.k_P, shell.x, shell.y)
        write(frame, body.t)
        return {**result.record, **shell_record(shell, result.report),
                "shell_start_repaired": repaired,
                **coupling_record(shell, result.iterations, result.change,
                                  result.change <= options.rtol, coupled_force(shell, body))}

    return stage


def monolithic_stage(shell: Shell, body: Body, body_stage: Callable[[int], Mapping[str, Any]],
                     write: Writer) -> Callable[[int], StageRecord]:
    """Return the stage of the monolithic scheme: every body step is a :class:`CoupledStep`."""
    step = CoupledStep(shell, body)
    body.use_solve(step)
    step.set_force()  # a resumed run's shell (checkpointed x, y)

    def stage(frame: int) -> StageRecord:
        step.start_frame(frame)
        record = body_stage(frame)
        report = step.frame_report()
        write(frame, body.t)
        force_body = (step.B.T @ shell.force).sum(axis=0).tolist()
        return {**record, **shell_record(shell, report), "coupling_scheme": "monolithic",
                "coupling_joint_system": step.joint_system,
                **coupling_record(shell, report.iterations,
                                  report.grad_norm / max(shell.gradient_scale, 1e-300),
                                  report.converged, force_body)}

    return stage


__all__ = ["CoupledStep", "coupled_force", "coupling_record", "monolithic_stage",
           "penalty_coupling", "two_way_stage"]
