"""Two-way coupling of the shell with the body, as one stage replacing both per frame.

Remillard & Kry 2013 couple skin and body both ways: the cluster penalty ``k_P ||H (x - y(u))||^2``
acts on the body too. The frame iterates body step and shell solve to the coupled state
(:func:`solvers.coupling.coupled_frame`); the record adds the coupling iterations, the last
change, whether it converged, and the penalty's total force on shell and body (equal, since
the rows of B sum to 1).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from models.backend import MPI
from models.coupling import PenaltyCoupling, body_force_function, penalty_force
from solvers.body import Body
from solvers.coupling import coupled_frame, explicit_frame
from wrinkles.shell_output import Writer
from wrinkles.shell_setup import Shell
from wrinkles.shell_stage import StageRecord, shell_record, solve_shell, target


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


def apply_force(shell: Shell, body: Body) -> None:
    """Make the shell's relaxed force ``shell.force`` the body's nodal load ``B^T f``."""
    body.set_nodal_load(body_force_function(shell.embedding, shell.force, body.V))


def feed_back(shell: Shell, body: Body) -> None:
    """Relax the penalty force of the current shell into the body's nodal load ``B^T f``."""
    omega = shell.options.internals.coupling.relaxation
    op = shell.energy.penalty_operator  # built once (None when k_P = 0: then H, zero force)
    f = penalty_force(op if op is not None else shell.clusters.H, shell.params.k_P, shell.x,
                      shell.y)
    shell.force = (1.0 - omega) * shell.force + omega * f
    apply_force(shell, body)


def explicit_stage(shell: Shell, body: Body, body_stage: Callable[[int], Mapping[str, Any]],
                   write: Writer) -> Callable[[int], StageRecord]:
    """Return the stage of the explicit scheme (:func:`solvers.coupling.explicit_frame`)."""
    options, comm = shell.options.internals.coupling, body.mesh.comm

    def stage(frame: int) -> StageRecord:
        x_start, y_start = shell.x.copy(), shell.y.copy()
        repaired = 0

        def solve() -> Any:
            nonlocal repaired
            report = solve_shell(shell, target(shell, body), frame, comm)
            repaired += shell.start_repaired
            return report

        def reset() -> None:
            shell.x, shell.y = x_start.copy(), y_start.copy()

        result = explicit_frame(body, options, lambda: body_stage(frame), solve,
                                lambda: feed_back(shell, body), reset)
        write(frame, body.t)
        return {**result.record, **shell_record(shell, result.report),
                "shell_start_repaired": repaired,
                **coupling_record(shell, result.iterations, result.change, options.rtol,
                                  body.applied_load().tolist())}

    return stage


def two_way_stage(shell: Shell, body: Body, body_stage: Callable[[int], Mapping[str, Any]],
                  write: Writer) -> Callable[[int], StageRecord]:
    """Return the stage of the scene's two-way scheme (implicit: :func:`coupled_frame`)."""
    options, comm = shell.options.internals.coupling, body.mesh.comm
    if options.scheme == "explicit":
        return explicit_stage(shell, body, body_stage, write)

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
                **coupling_record(shell, result.iterations, result.change, options.rtol,
                                  coupled_force(shell, body))}

    return stage


__all__ = ["apply_force", "coupled_force", "coupling_record", "explicit_stage", "feed_back",
           "penalty_coupling", "two_way_stage"]
