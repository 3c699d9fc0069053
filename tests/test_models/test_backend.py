"""PETSc's log is begun at import on every rank, so a serial solve on rank 0 alone cannot hang.

``models.backend.begin_petsc_log`` runs the collective ``PETSc.Log.begin()`` once at import;
``solvers.linear`` only reads the factorisation events. The 2-rank case builds and factorises a
``SparseDirectSolver`` (MUMPS Cholesky) on rank 0 only; both ranks must finish, the solve must
be exact and the analysis / numeric split must still be measured (analysis reused the 2nd time).
"""

from __future__ import annotations

import re

import pytest

from models.backend import PETSc, begin_petsc_log


def test_log_is_active_after_import_and_begin_is_idempotent():
    assert PETSc.Log.isActive()
    begin_petsc_log()
    assert PETSc.Log.isActive()


@pytest.mark.mpi
def test_rank0_only_sparse_solve_does_not_deadlock(mpiexec):
    proc = mpiexec(["tests/rank0_solve_case.py"], n=2, timeout=120)
    print(proc.stdout)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.split("\n")
    # the ranks share stdout and their prints may interleave: find the records, not lines
    assert sorted(re.findall(r"done \d", proc.stdout)) == ["done 0", "done 1"]
    reports = [line.split()[1:] for line in lines if line.startswith("rank0")]
    assert len(reports) == 2
    for residual, _, numeric, _ in reports:
        assert float(residual) < 1e-12
        assert float(numeric) > 0.0
    assert float(reports[0][1]) > 0.0 and reports[0][3] == "False"
    assert float(reports[1][1]) == 0.0 and reports[1][3] == "True"
