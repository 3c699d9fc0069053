"""PETSc's log is begun at import on every rank, so a serial solve on rank 0 alone cannot hang.

``models.backend.begin_petsc_log`` runs the collective ``PETSc.Log.begin()`` once at import;
``solvers.linear`` only reads the factorisation events. The 2-rank case builds and factorises a
``SparseDirectSolver`` (MUMPS Cholesky) on rank 0 only; both ranks must finish, the solve must
be exact and the analysis / numeric split must still be measured (analysis reused the 2nd time).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from models.backend import (
    MPI,
    PETSc,
    assemble_snes_residual,
    begin_petsc_log,
    dolfinx,
    ufl,
    vector_space,
)


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


def _hyperelastic_residual():
    """A neo-Hookean box pinned at x = 0 to a moved face: ``(u, F, J, bcs, b)``."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 1, 1]], [3, 3, 3],
                                   dolfinx.mesh.CellType.tetrahedron)
    V = vector_space(mesh, 1)
    u = dolfinx.fem.Function(V)
    F = ufl.Identity(3) + ufl.grad(u)
    J, C = ufl.det(F), F.T * F
    energy = (0.5 * (ufl.tr(C) - 3) - ufl.ln(J) + 2.0 * ufl.ln(J) ** 2) * ufl.dx
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    forms = [dolfinx.fem.form(f) for f in (residual, ufl.derivative(
        residual, u, ufl.TrialFunction(V)))]
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(np.array([0.02, -0.01, 0.03]),
                                 dolfinx.fem.locate_dofs_topological(V, 2, facets), V)
    u.interpolate(lambda x: np.stack([0.05 * x[1] * x[2], 0.02 * x[0] ** 2, -0.03 * x[1]]))
    b = dolfinx.fem.petsc.create_vector(V)
    return u, forms[0], forms[1], [bc], b


@pytest.mark.parametrize("meets", [True, False])
def test_snes_residual_equals_dolfinx_with_or_without_the_lifting(meets, monkeypatch):
    """Bit for bit dolfinx's ``assemble_residual``; dolfinx's own path only where the
    iterate is off its Dirichlet values (a start that meets them skips the lifting)."""
    u, residual, jacobian, bcs, b = _hyperelastic_residual()
    if meets:
        bcs[0].set(u.x.array)
    x = u.x.petsc_vec.copy()
    expected = b.duplicate()
    dolfinx.fem.petsc.assemble_residual(None, x, expected, u, residual, jacobian, bcs)
    calls = []
    original = dolfinx.fem.petsc.assemble_residual
    monkeypatch.setattr(dolfinx.fem.petsc, "assemble_residual",
                        lambda *args: calls.append(1) or original(*args))
    assemble_snes_residual(x, b, u, residual, jacobian, bcs, b.duplicate())
    assert np.array_equal(b.array, expected.array)
    assert np.abs(expected.array).max() > 1e-3  # a residual that is not zero
    assert len(calls) == (0 if meets else 1)
