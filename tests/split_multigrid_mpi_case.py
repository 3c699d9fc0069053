"""Run under ``mpiexec -n N``: the distributed multigrid Newton against the serial one.

A 21 x 21 plate (a 5 x 5 grid subdivided twice) held by a low-rank penalty to its compressed
self (:func:`shellcases.compressed_plate`), solved by the serial :class:`ShellNewtonSolver`
with multigrid CG and by :class:`SplitNewtonSolver` with the distributed multigrid, the
same options (fixed forcing ``--rtol``, no phase space, no fallback). Also checks one
preconditioned operator product against the serial ``A + G^T G``, the level below the fine
one against scipy's product and, with ``--phase-space``, ``A_Z`` against the serial one. Prints one
``RESULT {json}`` line on rank 0.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).parent))

import shellcases  # noqa: E402

from meshes.shells import grid_plate  # noqa: E402
from models.backend import MPI  # noqa: E402
from models.embedding.clusters import ClusterOptions, build_clusters  # noqa: E402
from solvers.decomposition.patch_energy import ShellProblem  # noqa: E402
from solvers.decomposition.split_newton import SplitNewtonSolver  # noqa: E402
from solvers.linear import AugmentedPenaltySolver  # noqa: E402
from solvers.multigrid import MultigridOptions, ShellHierarchy  # noqa: E402
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver  # noqa: E402


def _operator_difference(split: SplitNewtonSolver, energy, x: np.ndarray) -> float:  # noqa: ANN001
    """``max |K v - K_serial v| / max |K_serial v|`` of the distributed fine operator at x.

    ``K = A + tau I + G^T G`` with the split energy's Hessian rows (tau = 0.5), applied to a
    random vector in PETSc's distributed numbering, against the serial energy's.
    """
    comm = split.comm
    linear = split.linear
    linear.factorize(split.energy.evaluate(x, order=2), 0.5)
    ev = energy.evaluate(x, order=2)
    v = np.random.default_rng(7).standard_normal(x.size)
    ref = ev.hess @ v + 0.5 * v + ev.penalty_factor.T @ (ev.penalty_factor @ v)
    op = linear._operators[-1]  # noqa: SLF001 (the operator under test)
    owned = linear.levels[-1].owned
    vin, vout = op.createVecs()
    vin.setArray(v[owned])
    op.mult(vin, vout)
    diff = comm.allreduce(float(np.abs(vout.getArray() - ref[owned]).max()), op=MPI.MAX)
    return diff / float(np.abs(ref).max())


def _galerkin_difference(split: SplitNewtonSolver, energy, x: np.ndarray,  # noqa: ANN001
                         prolongation) -> float:  # noqa: ANN001
    """``max |C v - C_serial v| / max |C_serial v|`` of the level below the fine one at x.

    ``C`` summed from every rank's Hessian rows (:class:`SplitGalerkin`), against the serial
    ``P^T (A + tau I) P`` (scipy, tau = 0.5), for a random coarse vector.
    """
    comm, linear = split.comm, split.linear
    linear.factorize(split.energy.evaluate(x, order=2), 0.5)
    hess = energy.evaluate(x, order=2).hess
    ref_matrix = prolongation.T @ (hess + 0.5 * sp.identity(hess.shape[0])) @ prolongation
    v = np.random.default_rng(11).standard_normal(ref_matrix.shape[0])
    ref = ref_matrix @ v
    owned = linear.levels[-2].owned
    mat = linear._galerkin[-1]  # noqa: SLF001 (the level under test)
    vin, vout = mat.createVecs()
    vin.setArray(v[owned])
    mat.mult(vin, vout)
    diff = comm.allreduce(float(np.abs(vout.getArray() - ref[owned]).max()), op=MPI.MAX)
    return diff / float(np.abs(ref).max())


def _phase_difference(split: SplitNewtonSolver, serial: ShellNewtonSolver, energy,  # noqa: ANN001
                      x: np.ndarray) -> float:
    """``max |A_Z - A_Z,serial| / max |A_Z,serial|`` of the phase space's Galerkin matrix at x.

    ``A_Z = Z^T (A + tau I + G^T G) Z`` (tau = 0.5) summed over the ranks, its columns mapped
    from PETSc's numbering to the serial one, against the serial solver's.
    """
    comm, target = split.comm, np.asarray(energy.target)
    for solver, ev in ((serial, energy.evaluate(x, order=2)),
                       (split, split.energy.evaluate(x, order=2))):
        solver.linear.set_state(x, target)
        solver.linear.factorize(ev, 0.5)
    ref_phase, phase = serial.linear.phase, split.linear.phase
    ref = ref_phase._sum.matrix(ref_phase._base[0])  # noqa: SLF001 (the matrices under test)
    mine = phase._sum.matrix(phase._base[0]).toarray()  # noqa: SLF001
    held = np.full(ref.shape[0], -1, dtype=np.int64)
    held[phase.column] = phase._held[1]  # noqa: SLF001 (serial column -> PETSc column)
    petsc_of = np.empty_like(held)
    comm.Allreduce(held, petsc_of, op=MPI.MAX)
    diff = np.abs(mine[np.ix_(petsc_of, petsc_of)] - ref.toarray()).max()
    return float(comm.allreduce(diff, op=MPI.MAX) / np.abs(ref.data).max())


def _shift_difference(split: SplitNewtonSolver, x: np.ndarray) -> float:
    """Largest relative difference of the coarse levels shifted 0.5 -> 2 against new products.

    A retry of the same matrix with another shift moves the levels' shift
    (:func:`solvers.multigrid.shift_images`); ``A_l v`` for a random v on
    every level, against the levels recomputed at the new shift.
    """
    linear, comm = split.linear, split.comm
    ev = split.energy.evaluate(x, order=2)
    linear.factorize(ev, 0.5)
    linear.factorize(ev, 2.0)
    levels = linear._galerkin  # noqa: SLF001 (the levels under test)
    rng = np.random.default_rng(3)
    vectors = [m.createVecs() for m in levels]
    shifted = []
    for m, (vin, vout) in zip(levels, vectors, strict=True):
        vin.setArray(rng.standard_normal(vin.getLocalSize()))
        m.mult(vin, vout)
        shifted.append(vout.getArray().copy())
    linear.factorize(split.energy.evaluate(x, order=2), 2.0)  # a new evaluation: new products
    worst = 0.0
    for m, (vin, vout), ref in zip(linear._galerkin, vectors, shifted, strict=True):  # noqa: SLF001
        m.mult(vin, vout)
        scale = comm.allreduce(float(np.abs(vout.getArray()).max()), op=MPI.MAX)
        diff = comm.allreduce(float(np.abs(vout.getArray() - ref).max()), op=MPI.MAX)
        worst = max(worst, diff / scale)
    return worst


def _one_step(split: SplitNewtonSolver, energy, x: np.ndarray,  # noqa: ANN001
              tau: float) -> dict:
    """One distributed CG solve of ``(A + tau I + G^T G) dx = -g`` at x against a direct one.

    ``A`` is the Gauss-Newton Hessian (positive semi-definite: CG meets no negative
    curvature). Returns the relative gap to the serial direct solve (MUMPS on the augmented
    penalty system), the CG iterations and the coarse level's PC type (rank 0's).
    """
    ev = energy.evaluate(x, order=2, hessian="gauss_newton")
    shifted = (ev.hess + tau * sp.identity(ev.hess.shape[0])).tocsr()
    direct = AugmentedPenaltySolver(shifted, ev.penalty_factor)
    direct.factorize(shifted, ev.penalty_factor)
    dx_ref = direct.solve(-ev.grad)
    linear = split.linear
    linear.factorize(split.energy.evaluate(x, order=2, hessian="gauss_newton"), tau)
    dx = linear.solve(-ev.grad)
    return {"ranks": split.comm.size, "cg": linear.stats.iterations[-1],
            "gap": float(np.linalg.norm(dx - dx_ref) / np.linalg.norm(dx_ref)),
            "coarse_pc": linear._ksp.getPC().getMGCoarseSolve().getPC().getType()}  # noqa: SLF001


def main() -> None:
    """Solve both ways; print the comparison on rank 0."""
    parser = argparse.ArgumentParser()
    parser.add_argument("--hessian", choices=["gauss_newton", "exact"], default="exact")
    parser.add_argument("--rtol", type=float, default=1e-8)
    parser.add_argument("--forcing", choices=["fixed", "eisenstat_walker"], default="fixed")
    parser.add_argument("--phase-space", action="store_true")
    parser.add_argument("--eigen-estimate", choices=["setup", "solve"], default="setup")
    parser.add_argument("--grid", type=int, default=5, help="coarse plate cells per side")
    parser.add_argument("--levels", type=int, default=2, help="subdivision levels")
    parser.add_argument("--one-step", type=float, default=None, metavar="TAU",
                        help="only one CG solve at shift TAU against the direct solve")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    hier = ShellHierarchy.build(*grid_plate(args.grid, args.grid), levels=args.levels)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=20)
    clusters = build_clusters(hier.vertices, hier.faces, ClusterOptions(count=20))
    options = ShellNewtonOptions(
        rtol=1e-9, hessian=args.hessian, far_hessian="gauss_newton", linear_method="multigrid",
        gradient_scale=float(np.linalg.norm(energy.evaluate(x0, order=1).grad)),
        multigrid=MultigridOptions(rtol=args.rtol, forcing=args.forcing, fallback=False,
                                   phase_space=args.phase_space,
                                   eigen_estimate=args.eigen_estimate))
    problem = ShellProblem(energy.topology, energy.rest, energy.params, clusters.H,
                           np.asarray(energy.target))
    split = SplitNewtonSolver(problem, clusters.partition, options, comm,
                              prolongations=hier.prolongations())
    if args.one_step is not None:
        result = _one_step(split, energy, x0, args.one_step)
        if comm.rank == 0:
            print("RESULT " + json.dumps(result))
        return
    serial = ShellNewtonSolver(energy, options, hierarchy=hier)
    x_ref, ref = serial.minimize(x0)
    x, rep = split.minimize(x0)
    spread = comm.allreduce(float(np.abs(x - comm.bcast(x, root=0)).max()), op=MPI.MAX)
    operator_rel = _operator_difference(split, energy, x0)
    shift_rel = _shift_difference(split, x0)
    galerkin_rel = _galerkin_difference(split, energy, x0, hier.prolongations()[-1])
    phase_rel = _phase_difference(split, serial, energy, x0) if args.phase_space else 0.0
    if comm.rank == 0:
        print("RESULT " + json.dumps({
            "ranks": comm.size, "converged": rep.converged, "iterations": rep.iterations,
            "iterations_ref": ref.iterations, "cg": rep.krylov_iterations,
            "cg_ref": ref.krylov_iterations,
            "energy_rel": abs(rep.energy - ref.energy) / abs(ref.energy),
            "max_diff": float(np.abs(x - x_ref).max()),
            "wrinkle": float(np.abs(x_ref[:, 2]).max()), "rank_spread": spread,
            "operator_rel": operator_rel, "shift_rel": shift_rel,
            "galerkin_rel": galerkin_rel, "phase_rel": phase_rel}))


if __name__ == "__main__":
    main()
