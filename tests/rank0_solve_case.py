"""MPI case of tests/test_models/test_backend.py: a serial sparse solve on rank 0 only.

Before the fix ``SparseDirectSolver`` called the collective ``PETSc.Log.begin()`` in its
constructor, so building it on rank 0 alone hung rank 0 while rank 1 waited in the barrier.
Prints ``rank0 <residual> <analysis_time> <numeric_time> <reused>`` for two factorisations.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from models.backend import MPI
from solvers.linear import LinearSolverOptions, SparseDirectSolver


def laplacian_3d(n: int) -> sp.csr_matrix:
    """SPD 7-point Laplacian on an n^3 grid (Dirichlet), n^3 unknowns."""
    d = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.identity(n)
    return sp.csr_matrix(sp.kron(sp.kron(d, eye), eye) + sp.kron(sp.kron(eye, d), eye)
                         + sp.kron(sp.kron(eye, eye), d))


def main() -> None:
    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        A = laplacian_3d(12)
        b = np.random.default_rng(0).standard_normal(A.shape[0])
        solver = SparseDirectSolver(A, LinearSolverOptions(backend="mumps",
                                                           symmetric="cholesky"))
        for scale in (1.0, 2.0):
            report = solver.factorize(scale * A)
            x = solver.solve(b)
            res = np.linalg.norm(scale * A @ x - b) / np.linalg.norm(b)
            print(f"rank0 {res:.3e} {report.analysis_time:.6f} {report.numeric_time:.6f} "
                  f"{report.reused_analysis}", flush=True)
    comm.barrier()
    print(f"done {comm.rank}", flush=True)


if __name__ == "__main__":
    main()
