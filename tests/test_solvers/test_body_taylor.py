"""Taylor tests: the residual and Jacobian SNES uses are the derivatives of the energy it
line-searches on (elastic + inertia + gravity + sphere contact, P1 and P2, implicit Euler), and
the one-point strain energy of P1 equals the degree-2 quadrature's."""

from __future__ import annotations

import numpy as np
import pytest

from models.backend import MPI, PETSc, dolfinx, ufl
from models.body import BodyOptions
from models.contact import ContactOptions
from models.materials import Material
from solvers.body import Body


@pytest.mark.parametrize("degree", [1, 2])
def test_residual_and_jacobian_are_derivatives_of_the_energy(rng, degree):
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    sphere = ContactOptions(obstacle="sphere", point=(0.5, 0.5, 1.25), radius=0.3)
    opts = BodyOptions(degree=degree, dynamics="implicit_euler", dt=0.01, contacts=(sphere,))
    body = Body(mesh, Material(model="neo_hookean", E=1e5, nu=0.3), opts)
    body.v.x.array[:] = 0.1 * rng.standard_normal(body.v.x.array.size)
    body._predict(opts.dt)  # sets u_pred and the inertia weight of the incremental potential
    X = body.V.tabulate_dof_coordinates()
    body.u.x.array[:] = (0.02 * rng.standard_normal(X.shape)
                         + np.outer(X[:, 2], [0.0, 0.0, 0.1])).reshape(-1)
    solver = body._dynamic_solver
    problem = solver.problem
    u0 = body.u.x.array.copy()
    du = rng.standard_normal(u0.size) * 0.01
    assert body.reaction_force()[2] < 0.0  # the sphere penetrates: contact is active

    def energy_and_residual(u: np.ndarray) -> tuple[float, np.ndarray]:
        body.u.x.array[:] = u
        b = dolfinx.fem.petsc.assemble_vector(problem.F)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return solver.energy(), b.array.copy()

    pi0, r0 = energy_and_residual(u0)
    body.u.x.array[:] = u0
    A = dolfinx.fem.petsc.assemble_matrix(problem.J)
    A.assemble()
    dvec = A.createVecRight()
    n_owned = dvec.getLocalSize()
    dvec.array[:] = du[:n_owned]
    jdu = A.createVecLeft()
    A.mult(dvec, jdu)
    eps = 1e-2 * 0.5 ** np.arange(6)
    e1, e2 = [], []
    for h in eps:
        pi, r = energy_and_residual(u0 + h * du)
        e1.append(abs(pi - pi0 - h * MPI.COMM_WORLD.allreduce(r0 @ du[:n_owned])))
        e2.append(np.linalg.norm(r - r0 - h * jdu.array))
    s1 = np.polyfit(np.log(eps), np.log(e1), 1)[0]
    s2 = np.polyfit(np.log(eps), np.log(e2), 1)[0]
    print(f"energy Taylor remainders {np.array(e1)} slope {s1:.3f}; "
          f"residual remainders {np.array(e2)} slope {s2:.3f}")
    assert s1 > 1.9
    assert s2 > 1.8


def test_one_point_strain_energy_of_p1_equals_the_degree_two_quadrature(rng):
    """On affine P1 cells psi(F) is constant: the body's one-point strain energy, its gradient
    and its Hessian equal those of a degree-2 (4-point) quadrature to round-off."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 3, 3, 3)
    body = Body(mesh, Material(model="neo_hookean", E=1e5, nu=0.3), BodyOptions(degree=1))
    X = body.V.tabulate_dof_coordinates()
    body.u.x.array[:] = (0.03 * rng.standard_normal(X.shape)
                         + np.outer(X[:, 0], [-0.2, 0.05, 0.1])).reshape(-1)
    assert body.options.elastic_qdegree(affine=True) == 0
    assert body.options.elastic_qdegree(affine=False) == body.options.qdegree == 2
    w, du = ufl.TestFunction(body.V), ufl.TrialFunction(body.V)
    dx4 = ufl.Measure("dx", domain=mesh, metadata={"quadrature_degree": 2})
    one = body._energy_terms()["elastic"]
    four = body.material.psi(body.deformation_gradient()) * dx4
    values = []
    for energy in (one, four):
        gradient = ufl.derivative(energy, body.u, w)
        b = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(gradient))
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        A = dolfinx.fem.petsc.assemble_matrix(
            dolfinx.fem.form(ufl.derivative(gradient, body.u, du)))
        A.assemble()
        values.append((MPI.COMM_WORLD.allreduce(dolfinx.fem.assemble_scalar(
            dolfinx.fem.form(energy))), b, A))
    (e1, b1, A1), (e4, b4, A4) = values
    b1.axpy(-1.0, b4)
    A1.axpy(-1.0, A4)
    print(f"energy {e1:.15e} vs {e4:.15e}; |db|/|b| {b1.norm() / b4.norm():.2e}, "
          f"|dA|/|A| {A1.norm() / A4.norm():.2e}")
    assert e1 == pytest.approx(e4, rel=1e-13) and e1 > 0.0
    assert b1.norm() <= 1e-13 * b4.norm() and A1.norm() <= 1e-13 * A4.norm()
