"""The quadratic-term hook of the body's Newton (``EnergyNewton.set_quadratic_term``).

A quadratic energy ``1/2 int |grad u|^2 dX - int f.u dX`` on a small box (clamped face
x = 0) plus ``1/2 u^T K u - c^T u`` with a random SPD ``K`` whose pattern is *not* in the
finite-element pattern (random far-apart couplings): Newton must return the solution of the
reduced linear system ``(A + K)_ff u_f = (b + c)_f`` computed independently with scipy, in
one Newton step (exact Jacobian), and the objective must include the term.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from meshes.errors import InputError
from models.backend import MPI, PETSc, dolfinx, ufl, vector_space
from models.quadratic import QuadraticTerm
from solvers.body_newton import EnergyNewton, NewtonOptions


def petsc_csr(M: sp.csr_matrix) -> PETSc.Mat:
    M = M.tocsr()
    M.sort_indices()
    mat = PETSc.Mat().createAIJ(size=M.shape, csr=(M.indptr.astype(PETSc.IntType),
                                                   M.indices.astype(PETSc.IntType), M.data),
                                comm=MPI.COMM_SELF)
    mat.assemble()
    return mat


def test_newton_with_quadratic_term_matches_direct_solve():
    mesh = dolfinx.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 1, 1]], [3, 3, 3],
                                   dolfinx.mesh.CellType.tetrahedron)
    V = vector_space(mesh, 1)
    u = dolfinx.fem.Function(V)
    f = dolfinx.fem.Constant(mesh, np.array([3e-3, -2e-3, 5e-3]))
    energy = (0.5 * ufl.inner(ufl.grad(u), ufl.grad(u)) - ufl.dot(f, u)) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[0], 0.0))
    dofs = dolfinx.fem.locate_dofs_topological(V, 2, facets)
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dofs, V)
    det_f = ufl.det(ufl.Identity(3) + ufl.grad(u))
    solver = EnergyNewton(energy, u, [bc], det_f, 1, NewtonOptions(rtol=1e-12, atol=1e-12), 1.0)
    n = u.x.array.size
    rng = np.random.default_rng(3)
    P = sp.random(n // 2, n, density=4.0 / n, random_state=4, format="csr")
    K = (10.0 * P.T @ P + sp.identity(n)).tocsr()
    c = 1e-3 * rng.standard_normal(n)
    cv = PETSc.Vec().createWithArray(c.copy(), comm=MPI.COMM_SELF)
    solver.set_quadratic_term(QuadraticTerm(petsc_csr(K), cv, 0.25))
    result = solver.solve()
    # independent reference: assemble A and b of the FE energy with dolfinx/scipy
    w, du = ufl.TestFunction(V), ufl.TrialFunction(V)
    a = dolfinx.fem.assemble_matrix(dolfinx.fem.form(ufl.inner(ufl.grad(du), ufl.grad(w))
                                                     * ufl.dx)).to_scipy()
    b = dolfinx.fem.assemble_vector(dolfinx.fem.form(ufl.dot(f, w) * ufl.dx)).array
    free = np.setdiff1d(np.arange(n), bc.dof_indices()[0])
    S = (a + K).tocsr()[free][:, free]
    ref = np.zeros(n)
    ref[free] = sla.spsolve(S.tocsc(), (b + c)[free])
    err = np.abs(u.x.array - ref).max() / np.abs(ref).max()
    expected = (0.5 * ref @ (a @ ref) - b @ ref) + 0.5 * ref @ (K @ ref) - c @ ref + 0.25
    print(f"iterations {result.iterations}, relative error {err:.2e}, energy "
          f"{result.energy:.12e} expected {expected:.12e}, far couplings "
          f"{(K.nnz - K.multiply(a != 0).nnz)}")
    assert result.converged and result.iterations <= 2
    assert err < 1e-10
    assert result.energy == pytest.approx(expected, rel=1e-10)
    assert K.nnz - K.multiply(a != 0).nnz > 0  # the term widens the Jacobian's pattern


def test_block_jacobian_of_mumps_solves_as_the_scalar_one_of_superlu():
    """MUMPS gets the Jacobian as 3 x 3 blocks (BAIJ), SuperLU_dist as scalars (AIJ): a
    compressed, sphere-dented neo-Hookean box takes the same Newton steps to the same u."""
    from models.body import BodyOptions, PinSpec
    from models.contact import ContactOptions
    from models.materials import Material
    from solvers.body import Body

    results = []
    for package in ("mumps", "superlu_dist"):
        mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 3, 3, 3)
        pins = (PinSpec(point=(0, 0, 0), normal=(0, 0, 1)),
                PinSpec(point=(0, 0, 1), normal=(0, 0, 1), velocity=(0.0, 0.0, -0.5)))
        sphere = ContactOptions(obstacle="sphere", point=(1.25, 0.5, 0.5), radius=0.3)
        options = BodyOptions(dynamics="static", dt=0.2, gravity=(0, 0, 0), pins=pins,
                              contacts=(sphere,))
        body = Body(mesh, Material(model="neo_hookean", E=1e4, nu=0.3), options,
                    NewtonOptions(linear_solver=package))
        kind = body._static_solver.problem.A.getType()
        report = body.step()
        results.append((kind, report, body.u.x.array.copy()))
    (kind_m, rep_m, u_m), (kind_s, rep_s, u_s) = results
    print(f"mumps {kind_m} {rep_m}; superlu_dist {kind_s} {rep_s}")
    assert kind_m.endswith("baij") and kind_s.endswith("aij") and not kind_s.endswith("baij")
    assert NewtonOptions(petsc={"pc_type": "gamg"}).matrix_kind == "aij"
    assert rep_m.newton_iterations == rep_s.newton_iterations >= 2 and rep_m.contact > 0.0
    assert np.max(np.abs(u_m - u_s)) <= 1e-10 * np.max(np.abs(u_s)) and np.max(np.abs(u_s)) > 0


def box_problem(petsc: dict[str, object], load: float = 1e-3
                ) -> tuple[EnergyNewton, dolfinx.fem.Function]:
    """The Poisson-like vector energy of a 2^3 box, clamped at x = 0, with expert options."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 2, 2, 2)
    V = vector_space(mesh, 1)
    u = dolfinx.fem.Function(V)
    f = dolfinx.fem.Constant(mesh, np.array([1.0, 0.0, -2.0]) * load)
    energy = (0.5 * ufl.inner(ufl.grad(u), ufl.grad(u)) - ufl.dot(f, u)) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, facets),
                                 V)
    det_f = ufl.det(ufl.Identity(3) + ufl.grad(u))
    return EnergyNewton(energy, u, [bc], det_f, 1, NewtonOptions(petsc=petsc), 1.0), u


@pytest.mark.parametrize(("petsc", "named"), [
    ({"ksp_type": "nonsense"}, "Unable to find requested KSP type nonsense"),
    ({"ksp_type": "cg", "pc_type": "hypre"}, "Unable to find requested PC type hypre"),
    ({"ksp_rtoll": 1e-12}, "newton.options.petsc.ksp_rtoll = 1e-12: not read by PETSc"),
    ({"ksp_rtol": 1e-12}, "newton.options.petsc.ksp_rtol = 1e-12: not read"),  # preonly
])
def test_expert_petsc_options_refused_at_set_up_name_the_option(petsc, named):
    """PETSc's refusal (an unknown type) and an option nothing reads (a misspelt name, a
    Krylov tolerance of the default ``preonly`` solve) are InputErrors naming it, raised
    when the options are read (a scene's before any solver exists) and again by the solver
    given them anyway; the database is left without them and without a pushed prefix."""
    before = PETSc.Options().getAll()
    with pytest.raises(InputError) as info:
        NewtonOptions(petsc=petsc)
    print(info.value)
    assert named in str(info.value)
    assert PETSc.Options().getAll() == before
    unchecked = object.__new__(NewtonOptions)  # the fields without __post_init__'s check
    object.__setattr__(unchecked, "petsc", petsc)
    for name, value in vars(NewtonOptions()).items():
        if name != "petsc":
            object.__setattr__(unchecked, name, value)
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1)
    u = dolfinx.fem.Function(vector_space(mesh, 1))
    energy = 0.5 * ufl.inner(ufl.grad(u), ufl.grad(u)) * ufl.dx
    with pytest.raises(InputError, match=re.escape(named)):
        EnergyNewton(energy, u, [], ufl.det(ufl.Identity(3) + ufl.grad(u)), 1, unchecked)
    assert PETSc.Options().getAll() == before
    PETSc.Options()["probe_option"] = 1  # no prefix left pushed
    assert "probe_option" in PETSc.Options().getAll()
    PETSc.Options().delValue("probe_option")


def test_expert_petsc_options_of_the_factor_are_checked_at_the_first_solve():
    """Options read by the Krylov solver take effect; a MUMPS control is read by the factor
    at the first solve, and one that MUMPS does not know is refused there."""
    solver, u = box_problem({"ksp_type": "cg", "ksp_rtol": 1e-13, "mat_mumps_icntl_7": 5})
    ksp = solver.problem.solver.getKSP()
    assert ksp.getType() == "cg" and ksp.getTolerances()[0] == 1e-13
    result = solver.solve()
    assert result.converged and np.abs(u.x.array).max() > 0.0
    assert solver.problem.solver.getKSP().getPC().getFactorMatrix().getMumpsIcntl(7) == 5
    solver, u = box_problem({"mat_mumps_icntl_77777": 1}, load=0.0)
    assert solver.solve().iterations == 0  # solved at the start: no factor, nothing to check
    u.x.array[:] = 1e-3  # away from the solution (the clamp's rows included)
    with pytest.raises(InputError, match="mat_mumps_icntl_77777 = 1: not read by PETSc"):
        solver.solve()
