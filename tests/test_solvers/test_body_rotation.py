"""Rotating pins (``PinSpec.point / angular_velocity``): exact prescribed
rigid rotation of a pinned face, validation, and the Saint-Venant torsion of a cylinder.

Saint-Venant torsion of a circular cylinder (radius R, length L, shear modulus G) twisted by
a small angle theta between its end faces: the cross-sections rotate rigidly without
warping, so clamping both end faces is exact, and the torque is T = G J theta / L with
J = pi R^4 / 2 (Timoshenko & Goodier, Theory of Elasticity, ch. 10).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from meshes.errors import InputError
from models.backend import MPI, dolfinx
from models.body import BodyOptions, PinSpec
from solvers.body import Body
from validation.torsion import MAT, SHEAR, L, R, end_torque, twisted_cylinder


def test_rotation_matrix_is_rodrigues():
    pin = PinSpec(angular_velocity=(0.0, 0.0, 0.65))
    Q = pin.rotation(2.0)  # phi = 0.65 * 2 = 1.3 about z
    c, s = math.cos(1.3), math.sin(1.3)
    np.testing.assert_allclose(Q, [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], atol=1e-15)
    np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-15)


def test_pinned_face_rotates_exactly():
    """The pinned nodes of a box face carry exactly (R - I)(X - p) + v t after a step."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1.0, 0.4, 0.4]], [4, 2, 2])
    center, omega = (1.0, 0.2, 0.2), 0.3
    pins = (PinSpec(point=(0, 0, 0), normal=(1, 0, 0), tol=1e-9),
            PinSpec(point=center, normal=(1, 0, 0), tol=1e-9,
                    angular_velocity=(omega, 0.0, 0.0), velocity=(-0.01, 0.0, 0.0)))
    body = Body(mesh, MAT, BodyOptions(degree=2, dt=1.0, gravity=(0.0, 0.0, 0.0), pins=pins))
    body.step()
    X = body.V.tabulate_dof_coordinates()
    face = np.abs(X[:, 0] - 1.0) < 1e-9
    u = body.u.x.array.reshape(-1, 3)[face]
    phi = omega * 1.0
    c, s = math.cos(phi), math.sin(phi)
    arm = X[face] - np.array(center)
    rotated = np.column_stack([arm[:, 0], c * arm[:, 1] - s * arm[:, 2],
                               s * arm[:, 1] + c * arm[:, 2]])
    expected = rotated - arm + np.array([-0.01, 0.0, 0.0])
    np.testing.assert_allclose(u, expected, rtol=0, atol=1e-14)
    assert np.abs(expected).max() > 0.03  # a real rotation (0.3 rad over a 0.28 m arm)
    np.testing.assert_allclose(body.u.x.array.reshape(-1, 3)[np.abs(X[:, 0]) < 1e-9], 0.0)


def test_rotating_pin_holds_only_its_components():
    """components = (1, 2): the pinned face rotates in its plane, x stays free."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1.0, 0.4, 0.4]], [4, 2, 2])
    pins = (PinSpec(point=(0, 0, 0), normal=(1, 0, 0), tol=1e-9),
            PinSpec(point=(1.0, 0.2, 0.2), normal=(1, 0, 0), tol=1e-9,
                    components=(1, 2), angular_velocity=(0.2, 0.0, 0.0)))
    body = Body(mesh, MAT, BodyOptions(degree=1, dt=1.0, gravity=(0.0, 0.0, 0.0), pins=pins))
    body.step()
    X = body.V.tabulate_dof_coordinates()
    face = np.abs(X[:, 0] - 1.0) < 1e-9
    expected = pins[1].displacement_at(X[face], 1.0)
    u = body.u.x.array.reshape(-1, 3)[face]
    np.testing.assert_allclose(u[:, 1:], expected[:, 1:], rtol=0, atol=1e-14)
    assert np.abs(u[:, 0]).max() > 1e-5  # free axial component: the twisted bar shortens


@pytest.mark.parametrize(("key", "kwargs"), [
    ("pin.angular_velocity", {"angular_velocity": 1.0}),
    ("pin.angular_velocity", {"angular_velocity": (0.0, math.inf, 0.0)}),
    ("pin.point", {"point": (0.0, 1.0)}),
    ("pin.box", {"box": ((0.0, 0.0, 1.0), (1.0, 1.0, 0.0))}),
    ("pin.box", {"box": (0.0, 0.0, 1.0)}),
])
def test_rotating_pin_validation_names_the_key(key, kwargs):
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        PinSpec(**kwargs)


def test_saint_venant_torsion_p2():
    """Torque of a twisted P2 cylinder against T = G J theta / L as the mesh is refined.

    Measured (dolfinx 0.11, theta = 0.01): relative errors against the circular J of
    -5.5 %, -2.9 %, -1.4 % at h = 0.5, 0.35, 0.25 (fitted rate 1.9: the polygonal section
    loses area as O(h^2)); against the meshed section's J_h: -1.2e-4, -3.0e-5, -1.0e-5.
    """
    theta, sizes = 0.01, (0.5, 0.35, 0.25)
    exact = SHEAR * math.pi * R**4 / 2.0 * theta / L
    errors, errors_h = [], []
    for h in sizes:
        body, j_h = twisted_cylinder(h, theta)
        torque = end_torque(body, L)
        energy_torque = 2.0 * body.energies()["elastic"] / theta  # E = T theta / 2 (linear)
        assert abs(torque[2] / energy_torque - 1.0) < 1e-3
        assert np.hypot(torque[0], torque[1]) < 2e-3 * abs(torque[2])
        errors.append(torque[2] / exact - 1.0)
        errors_h.append(torque[2] / (SHEAR * j_h * theta / L) - 1.0)
    rate = np.polyfit(np.log(sizes), np.log(np.abs(errors)), 1)[0]
    print(f"torsion P2 h={sizes} rel. errors={np.round(errors, 5)} vs J_h="
          f"{np.round(errors_h, 5)} rate={rate:.2f}")
    assert abs(errors[-1]) < 0.02
    assert rate > 1.6
    assert max(abs(e) for e in errors_h) < 1e-3


def test_torque_is_linear_for_small_twist():
    """Doubling a small twist doubles the torque (geometric nonlinearity O(theta^2))."""
    torques = [end_torque(twisted_cylinder(0.5, theta)[0], L)[2] for theta in (0.01, 0.02)]
    print(f"torque ratio T(0.02)/T(0.01) = {torques[1] / torques[0]:.6f}")
    assert abs(torques[1] / torques[0] - 2.0) < 1e-4
