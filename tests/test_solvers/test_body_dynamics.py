"""Dynamics: energy behaviour of implicit Euler and Newmark, a block dropped on the ground."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError
from models.backend import MPI, dolfinx
from models.body import BodyOptions
from models.contact import ContactOptions
from models.materials import Material
from solvers.body import Body

MAT = Material(model="neo_hookean", E=1.0e5, nu=0.3, density=1000.0)


def free_block(dynamics: str, degree: int = 1) -> Body:
    """A free 1 x 0.5 x 0.5 m block with a stretching and twisting initial velocity."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1.0, 0.5, 0.5]], [4, 2, 2],
                                   dolfinx.mesh.CellType.tetrahedron)
    body = Body(mesh, MAT, BodyOptions(degree=degree, dynamics=dynamics, dt=0.005,
                                       gravity=(0, 0, 0)))
    body.v.interpolate(lambda x: np.array([0.5 * (x[0] - 0.5), -0.3 * (x[2] - 0.25),
                                           0.3 * (x[1] - 0.25)]))
    return body


def energy_history(body: Body, steps: int) -> np.ndarray:
    energies = [body.energies()["total"]]
    for _ in range(steps):
        report = body.step()
        assert report.converged and report.min_det_f > 0.0
        energies.append(report.energy)
    return np.asarray(energies)


def test_implicit_euler_never_increases_total_energy():
    energy = energy_history(free_block("implicit_euler"), 100)
    increase = np.max(np.diff(energy)) / energy[0]
    print(f"implicit Euler: E0={energy[0]:.6f} J, E100/E0={energy[-1] / energy[0]:.4f}, "
          f"max step increase/E0={increase:.2e}")
    assert increase <= 1e-10
    assert energy[-1] < 0.9 * energy[0]  # it dissipates, measurably


@pytest.mark.parametrize("degree", [1, 2])
def test_newmark_conserves_total_energy(degree):
    body = free_block("newmark", degree)
    energy = energy_history(body, 200)
    deviation = np.max(np.abs(energy - energy[0])) / energy[0]
    kinetic = body.energies()["kinetic"] / energy[0]
    print(f"Newmark P{degree}: E0={energy[0]:.6f} J, max |E - E0|/E0 over 200 steps = "
          f"{deviation:.2e}, final kinetic share {kinetic:.3f}")
    assert deviation < 0.01
    assert 0.01 < kinetic < 0.99  # energy really moves between kinetic and elastic


def test_dropped_block_comes_to_rest_with_reaction_equal_to_weight():
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0.01], [0.5, 0.5, 0.51]], [2, 2, 2],
                                   dolfinx.mesh.CellType.tetrahedron)
    opts = BodyOptions(dynamics="implicit_euler", dt=0.02, gravity=(0, 0, -9.81),
                       contacts=(ContactOptions(obstacle="plane"),))
    body = Body(mesh, MAT, opts)
    reports = [body.step() for _ in range(80)]
    weight = MAT.density * 0.125 * 9.81
    force = body.reaction_force()
    bottom = (body.V.tabulate_dof_coordinates() + body.u.x.array.reshape(-1, 3))[:, 2].min()
    print(f"after {body.t:.2f} s: reaction {force} N, weight {weight:.4f} N, rel.err "
          f"{abs(force[2] - weight) / weight:.2e}, kinetic {reports[-1].kinetic:.2e} J, "
          f"lowest point z={bottom:.2e} m, min det F={min(r.min_det_f for r in reports):.4f}")
    assert abs(force[2] - weight) / weight < 0.02
    assert np.linalg.norm(force[:2]) < 1e-6 * weight
    assert reports[-1].kinetic < 1e-6 * weight * 0.01
    assert -1e-3 < bottom < 0.0  # resting on the ground with a small penalty penetration


def test_sphere_contact_pushes_back_and_moves():
    """A sphere pressed into a clamped block: reaction along the centre line, grows with depth."""
    from models.body import PinSpec

    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 4, 4, 4)
    pins = (PinSpec(point=(0, 0, 0), normal=(0, 0, 1)),)
    sphere = ContactOptions(obstacle="sphere", point=(0.5, 0.5, 1.3), radius=0.32)
    body = Body(mesh, MAT, BodyOptions(gravity=(0, 0, 0), pins=pins, contacts=(sphere,)))
    forces = []
    for depth in (0.01, 0.02):
        body.set_sphere_center((0.5, 0.5, 1.32 - depth))
        body.solve_static()
        forces.append(body.reaction_force())
    print(f"sphere reaction at depth 1 cm: {forces[0]}, 2 cm: {forces[1]}")
    assert forces[1][2] < forces[0][2] < 0.0  # pushes the body down, harder when deeper
    assert np.all(np.abs(np.asarray(forces)[1, :2]) < 0.02 * abs(forces[1][2]))  # mesh asymmetry
    with pytest.raises(InputError, match="contact.radius"):
        ContactOptions(obstacle="sphere", radius=0.0)


def test_moving_pins_in_dynamics_follow_the_prescribed_motion():
    """Top face pushed down at 0.1 m/s (implicit Euler): pinned nodes move exactly as told,
    and the slow (quasi-static) compression ends near the static state at the same pin."""
    from models.body import PinSpec

    def block(dynamics: str) -> Body:
        mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 3, 3, 3)
        pins = (PinSpec(point=(0, 0, 0), normal=(0, 0, 1)),
                PinSpec(point=(0, 0, 1), normal=(0, 0, 1),
                        velocity=(0.0, 0.0, -0.1)))
        return Body(mesh, MAT, BodyOptions(dynamics=dynamics, dt=0.1, gravity=(0, 0, 0),
                                           pins=pins))

    moving = block("implicit_euler")
    for _ in range(20):
        moving.step()
    X = moving.V.tabulate_dof_coordinates()
    top = np.isclose(X[:, 2], 1.0)
    U, V = moving.u.x.array.reshape(-1, 3), moving.v.x.array.reshape(-1, 3)
    static = block("static")
    static.t = moving.t
    static.solve_static()
    diff = np.linalg.norm(moving.u.x.array - static.u.x.array) / np.linalg.norm(static.u.x.array)
    print(f"t={moving.t:.2f}: top w={U[top, 2].mean():.6f}, top v_z={V[top, 2].mean():.6f}, "
          f"|u_dyn - u_static|/|u_static|={diff:.2e}")
    assert np.allclose(U[top], [0.0, 0.0, -0.2], atol=1e-14)
    assert np.allclose(V[top], [0.0, 0.0, -0.1], atol=1e-12)
    assert diff < 1e-4


@pytest.mark.parametrize("dynamics", ["implicit_euler", "newmark"])
def test_step_from_a_guess_reaches_the_same_state_in_fewer_iterations(dynamics):
    """``Body.step(guess)`` starts Newton from ``guess`` instead of the predictor: from the
    step's own solution (perturbed by 1e-9 of its size) it takes one iteration against the
    predictor's 2 (measured, both schemes) and ends at
    the same state to the Newton tolerance; the kinematics (v) follow from the same u."""
    body = free_block(dynamics)
    for _ in range(3):
        body.step()
    saved = body.snapshot()
    plain = body.step()
    u, v = body.u.x.array.copy(), body.v.x.array.copy()
    body.restore(saved)
    guessed = body.step(u + 1e-9 * np.abs(u).max())
    print(dynamics, "iterations from the predictor", plain.newton_iterations,
          "from the guess", guessed.newton_iterations)
    assert guessed.newton_iterations <= 1 < plain.newton_iterations
    scale = np.abs(u).max()
    assert np.abs(body.u.x.array - u).max() <= 1e-8 * scale
    assert np.abs(body.v.x.array - v).max() <= 1e-8 * scale / body.options.dt  # v ~ u / dt
