"""A manufactured static solution of the Neo-Hookean body for mesh convergence rates.

The body force is ``-div P(F(u_e))`` of a smooth exact field ``u_e`` with strains ~10 %; the
L2 error of the P1 / P2 solution on a unit-cube mesh of ``n`` cells per side is fitted against
``h = 1/n`` (expected orders 2 and 3).
"""

from __future__ import annotations

import numpy as np

from models.backend import MPI, dolfinx, global_scalar, ufl, vector_space
from models.materials import Material
from solvers.body_newton import EnergyNewton, NewtonOptions

MAT = Material(model="neo_hookean", E=1.0e5, nu=0.3)


def exact_displacement(x):
    """Return the exact field: strains ~ 10 %, small but clearly nonlinear."""
    a = 0.05
    return ufl.as_vector([a * ufl.sin(np.pi * x[0]) * (1 + x[1]),
                          a * ufl.sin(np.pi * x[1]) * ufl.cos(np.pi * x[2]),
                          a * ufl.cos(np.pi * x[2]) * x[0] * x[1]])


def l2_error(n: int, degree: int) -> float:
    """Solve Pi(u) = int psi(F(u)) - f.u with u = u_ex on the boundary; return |u - u_ex|_L2."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, n, n, n)
    V = vector_space(mesh, degree)
    x = ufl.SpatialCoordinate(mesh)
    u_ex = exact_displacement(x)
    f = -ufl.div(MAT.first_piola(ufl.Identity(3) + ufl.grad(u_ex)))
    u = dolfinx.fem.Function(V)
    u.interpolate(dolfinx.fem.Expression(u_ex, V.element.interpolation_points))  # initial guess
    mesh.topology.create_connectivity(2, 3)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    bc_value = dolfinx.fem.Function(V)
    bc_value.x.array[:] = u.x.array
    bc = dolfinx.fem.dirichletbc(bc_value, dolfinx.fem.locate_dofs_topological(V, 2, facets))
    dx = ufl.dx(domain=mesh, metadata={"quadrature_degree": 2 * degree + 2})
    F = ufl.Identity(3) + ufl.grad(u)
    energy = MAT.psi(F) * dx - ufl.dot(f, u) * dx
    solver = EnergyNewton(energy, u, [bc], ufl.det(F), 2 * degree,
                          NewtonOptions(rtol=1e-11, atol=1e-10))
    result = solver.solve()
    assert result.converged, result.describe()
    dxe = ufl.dx(domain=mesh, metadata={"quadrature_degree": 2 * degree + 4})
    return float(np.sqrt(global_scalar(dolfinx.fem.form(ufl.dot(u - u_ex, u - u_ex) * dxe))))
