"""Saint-Venant torsion of a circular cylinder: the body's analytic check.

A cylinder of radius R and length L, one end clamped, the other rotated by ``theta`` about its
axis: for small twist the end torque is ``T = G J theta / L``, ``J = pi R^4 / 2`` (Timoshenko &
Goodier, Theory of Elasticity, ch. 10).
"""

from __future__ import annotations

import numpy as np

from meshes.builders import cylinder
from models.backend import MPI, dolfinx, global_scalar, mesh_from_arrays, ufl
from models.body import BodyOptions, PinSpec
from models.materials import Material
from solvers.body import Body

R, L = 1.0, 2.0
"""Radius and length of the cylinder [m]."""
MAT = Material(model="neo_hookean", E=1.0e4, nu=0.3)


SHEAR = MAT.E / (2.0 * (1.0 + MAT.nu))


def twist_pins(theta: float) -> tuple[PinSpec, PinSpec]:
    """Clamp z = 0; rotate the face z = L by ``theta`` per unit load parameter about z."""
    clamp = PinSpec(point=(0, 0, 0), normal=(0, 0, 1), tol=1e-6)
    twist = PinSpec(point=(0, 0, L), normal=(0, 0, 1), tol=1e-6,
                    angular_velocity=(0.0, 0.0, theta))
    return clamp, twist


def end_torque(body: Body, z: float) -> np.ndarray:
    """Moment about (0, 0, z) of the reaction forces on the nodes of the face at height z.

    The reaction on pinned dof i is the elastic residual ``dPi/du_i`` (the force the pin
    applies to hold the node); the moment uses the current positions ``X + u``.
    """
    w = ufl.TestFunction(body.V)
    form = ufl.derivative(body.material.psi(body.deformation_gradient()) * body.dx, body.u, w)
    residual = dolfinx.fem.assemble_vector(dolfinx.fem.form(form)).array.reshape(-1, 3)
    X = body.V.tabulate_dof_coordinates()
    x = X + body.u.x.array.reshape(-1, 3)
    face = np.abs(X[:, 2] - z) < 1e-6
    return np.cross(x[face] - np.array([0.0, 0.0, z]), residual[face]).sum(axis=0)


def twisted_cylinder(h: float, theta: float, degree: int = 2) -> tuple[Body, float]:
    """Twist the cylinder statically by ``theta``; return the body and the discrete J_h.

    ``J_h = int (x^2 + y^2) dX / L`` is the polar moment of the meshed (polygonal) section.
    """
    mesh_data = cylinder(R, L, h, "z")
    mesh = mesh_from_arrays(MPI.COMM_WORLD, mesh_data.points, mesh_data.tets)
    body = Body(mesh, MAT, BodyOptions(degree=degree, dt=1.0, gravity=(0.0, 0.0, 0.0),
                                       pins=twist_pins(theta)))
    body.step()
    x = ufl.SpatialCoordinate(mesh)
    j_h = global_scalar(dolfinx.fem.form((x[0] ** 2 + x[1] ** 2) * ufl.dx)) / L
    return body, float(j_h)
