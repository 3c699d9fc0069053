"""The whole problem, distributed: monolithic shell Newton with an MPIAIJ Hessian.

The reference parallel method against which the decomposition is measured (MISSION.md
section 7): the same Newton / SQP iteration as :mod:`solvers.shell_newton` (line search,
shifts, tolerance, all reused: this module only swaps its linear system), with

* the Hessian as a distributed PETSc ``MATMPIAIJ``, rows split by contiguous vertex ranges
  (rank r owns dofs ``3 v_r .. 3 v_{r+1} - 1``), its pattern set once by
  ``MatSetPreallocationCOO`` and its values refreshed by ``MatSetValuesCOO`` (constant
  nonzero state, so the parallel symbolic analysis is done once);
* a parallel direct solver, MUMPS (Cholesky / LDL^T with the inertia ``INFOG(12)``, or LU) or
  SuperLU_dist (LU), through ``KSPPREONLY`` + ``PCFactor``; the solution is allgathered.

Energy, gradient and Hessian are evaluated *redundantly* on every rank and each rank inserts
only its own rows (:mod:`.split_newton` splits the evaluation by stencils and keeps the penalty
low-rank; the assembled ``H^T H`` here fills in: 0.47x the serial low-rank solve at 10k
vertices on 2 ranks, contended machine, benchmarks/decomposition.py): every rank then runs
the identical Newton iteration in lockstep (same values, same line search decisions). The
time split (evaluation vs. factorisation vs. solve) is in the :class:`ShellSolveReport`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import MPI, PETSc
from solvers.linear import (
    FactorReport,
    LinearSolverOptions,
    coo_aij,
    factor_ksp,
    factor_status,
    setup_pc,
)
from solvers.shell_newton import (
    EnergyEval,
    ShellEnergyLike,
    ShellNewtonOptions,
    ShellNewtonSolver,
    ShellSolveReport,
)


def vertex_ranges(n_vertices: int, size: int) -> np.ndarray:
    """(size + 1,) vertex offsets of a balanced contiguous split."""
    return (np.arange(size + 1) * n_vertices) // size


class DistributedLinearSystem:
    """``(A + tau I) dx = b`` with A as MPIAIJ over ``comm``; the ShellNewtonSolver interface.

    Args:
        comm: mpi4py communicator.
        options: Backend ("mumps" or "superlu_dist") and factorisation.

    """

    def __init__(self, comm: Any, options: LinearSolverOptions) -> None:
        if options.backend not in ("mumps", "superlu_dist"):
            raise InputError(f"LinearSolverOptions.backend: the distributed solve needs "
                             f"'mumps' or 'superlu_dist', got {options.backend!r}")
        self.comm, self.options = comm, options
        self.mat: Any = None
        self.rhs: Any = None
        self.sol: Any = None
        self._times = [0.0, 0.0, 0.0]  # factorise, analysis, solve

    def _setup(self, hess: sp.csr_matrix) -> None:
        """Rows of this rank, COO preallocation, KSP + PCFactor (once)."""
        offsets = 3 * vertex_ranges(hess.shape[0] // 3, self.comm.size)
        r0, r1 = int(offsets[self.comm.rank]), int(offsets[self.comm.rank + 1])
        self._rows = (r0, r1)
        self._counts = np.diff(offsets).astype(np.int64)
        self._slice = slice(int(hess.indptr[r0]), int(hess.indptr[r1]))
        rows = np.repeat(np.arange(r0, r1), np.diff(hess.indptr[r0: r1 + 1]))
        cols = hess.indices[self._slice]
        self._diag = np.flatnonzero(rows == cols)
        mat = coo_aij(self.comm, r1 - r0, hess.shape[0], rows, cols)
        mat.setOption(PETSc.Mat.Option.SPD, self.options.symmetric == "cholesky")
        self.mat = mat
        self.ksp = self._create_ksp()
        vecs: Any = mat.createVecs()
        self.rhs, self.sol = vecs

    def _create_ksp(self) -> Any:
        """KSPPREONLY with PCFactor of the chosen backend.

        MUMPS gets the options' controls (ordering, BLR, refinement) and ICNTL(13) = 1: no
        ScaLAPACK on the root front, whose pivots INFOG(12) would not count, so the inertia
        test sees every negative eigenvalue on more than one rank (as the split solve).
        """
        icntl = ((13, 1),) if self.options.backend == "mumps" else None
        return factor_ksp(self.mat, self.options, self.comm, mumps_icntl=icntl)

    def factorize(self, ev: EnergyEval, tau: float) -> FactorReport:
        """Insert this rank's rows of ``A + tau I`` and factorise in parallel."""
        if ev.hess is None or ev.penalty_factor is not None:
            raise InputError("ShellParams.penalty_hessian: the distributed solve needs the "
                             "assembled Hessian ('assembled')")
        if self.mat is None:
            self._setup(ev.hess)
        values = np.array(ev.hess.data[self._slice], dtype=PETSc.ScalarType)
        values[self._diag] += tau
        self.mat.setValuesCOO(values)
        first = self._times[0] == 0.0
        pc = self.ksp.getPC()
        failed, error, elapsed = setup_pc(pc)
        self._times[0] += elapsed
        self._times[1] += elapsed if first else 0.0
        success, negatives, reason = factor_status(pc, failed, error, self.options)
        report = FactorReport(success=success, reason=reason, negative_pivots=negatives,
                              numeric_time=elapsed, shift=float(tau))
        if not report.success:
            # the factor keeps its error flag and PCSetUp would skip every later numeric
            # factorisation (all shifted retries failed at 10k vertices): start a fresh KSP
            self.ksp.destroy()
            self.ksp = self._create_ksp()
        return report

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve with the last factorisation; the full solution on every rank."""
        start = time.perf_counter()
        r0, r1 = self._rows
        self.rhs.setArray(np.ascontiguousarray(rhs[r0:r1]))
        self.ksp.solve(self.rhs, self.sol)
        full = np.empty(rhs.size)
        displs = np.concatenate([[0], np.cumsum(self._counts)[:-1]])
        self.comm.Allgatherv([np.ascontiguousarray(self.sol.getArray()), MPI.DOUBLE],
                             [full, self._counts, displs, MPI.DOUBLE])
        self._times[2] += time.perf_counter() - start
        return full

    def times(self) -> tuple[float, float, float]:
        """Accumulated (factorise, first factorisation incl. analysis, solve) seconds."""
        return self._times[0], self._times[1], self._times[2]


def distributed_minimize(energy: ShellEnergyLike, x0: np.ndarray,
                         options: ShellNewtonOptions | None = None,
                         comm: Any = None) -> tuple[np.ndarray, ShellSolveReport]:
    """Monolithic shell Newton with the distributed Hessian (see the module docstring).

    Args:
        energy: The global shell energy (assembled penalty Hessian), built on every rank.
        x0: (n, 3) start, the same on every rank.
        options: Newton options; ``options.linear`` picks MUMPS / SuperLU_dist.
        comm: Communicator (default COMM_WORLD).

    Returns:
        ``(x, report)``, identical on every rank.

    """
    opts = options or ShellNewtonOptions()
    solver = ShellNewtonSolver(energy, opts)
    solver.linear = DistributedLinearSystem(comm if comm is not None else MPI.COMM_WORLD,
                                            opts.linear)
    return solver.minimize(x0)
