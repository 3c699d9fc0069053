"""Materials and the static body: validation, closed-form stress, uniaxial stretch."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from meshes.errors import InputError
from models.backend import MPI, dolfinx, global_scalar, ufl
from models.body import BodyOptions, PinSpec
from models.materials import Material
from solvers.body import Body
from solvers.body_newton import NewtonOptions

STRETCH = 1.3


def test_material_validation_names_the_field():
    with pytest.raises(InputError, match="nu must be < 0.5"):
        Material(nu=0.5)
    for kwargs, name in [({"E": 0.0}, "E"), ({"density": -1.0}, "density"),
                         ({"nu": -1.0}, "nu"), ({"E": float("nan")}, "E"),
                         ({"model": "mooney"}, "model")]:
        with pytest.raises(InputError, match=name):
            Material(**kwargs)
    m = Material(E=1.0e5, nu=0.3)
    assert m.mu == pytest.approx(1.0e5 / 2.6, rel=1e-15)
    assert m.lmbda == pytest.approx(1.0e5 * 0.3 / (1.3 * 0.4), rel=1e-15)


@pytest.mark.parametrize("model", ["neo_hookean", "stvk"])
def test_closed_form_piola_equals_ufl_diff(model):
    """P(F) in closed form against ufl.diff(psi, F) on a nonlinear displacement field."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    x = ufl.SpatialCoordinate(mesh)
    u = ufl.as_vector([0.2 * x[1] * x[2], 0.1 * ufl.sin(x[0]), -0.15 * x[0] * x[1]])
    mat = Material(model=model, E=2.0e5, nu=0.35)
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    diff = mat.first_piola(F) - ufl.diff(mat.psi(F), F)
    dx = ufl.dx(metadata={"quadrature_degree": 4})
    err = global_scalar(dolfinx.fem.form(ufl.inner(diff, diff) * dx))
    ref = global_scalar(dolfinx.fem.form(ufl.inner(mat.first_piola(F), mat.first_piola(F)) * dx))
    print(f"{model}: |P_closed - P_diff| / |P| = {np.sqrt(err / ref):.3e}")
    assert np.sqrt(err / ref) < 1e-12


def uniaxial_reference(mat: Material, stretch: float) -> tuple[float, float]:
    """Lateral stretch s and P11 of uniaxial stress F = diag(stretch, s, s), P22 = 0."""
    mu, lam = mat.mu, mat.lmbda
    if mat.model == "neo_hookean":
        def p22(s):
            return mu * (s - 1 / s) + lam * np.log(stretch * s * s) / s

        s = brentq(p22, 0.3, 1.0 + 1e-12, xtol=1e-15, rtol=1e-15)
        return s, mu * (stretch - 1 / stretch) + lam * np.log(stretch * s * s) / stretch

    def s22(s):
        e11, e22 = 0.5 * (stretch**2 - 1), 0.5 * (s**2 - 1)
        return lam * (e11 + 2 * e22) + 2 * mu * e22

    s = brentq(s22, 0.3, 1.0 + 1e-12, xtol=1e-15, rtol=1e-15)
    e11, e22 = 0.5 * (stretch**2 - 1), 0.5 * (s**2 - 1)
    return s, stretch * (lam * (e11 + 2 * e22) + 2 * mu * e11)


def symmetry_pins(stretch: float) -> tuple[PinSpec, ...]:
    """Normal components held on x=0, y=0, z=0; the x=1 face moved to x = stretch at t = 1."""
    planes = [PinSpec(point=(0, 0, 0), normal=tuple(np.eye(3)[k]), components=(k,))
              for k in range(3)]
    moved = PinSpec(point=(1, 0, 0), normal=(1, 0, 0), components=(0,),
                    velocity=(stretch - 1.0, 0.0, 0.0))
    return (*planes, moved)


@pytest.mark.parametrize("model", ["neo_hookean", "stvk"])
def test_uniaxial_stretch_matches_closed_form(model):
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    mat = Material(model=model, E=1.0e5, nu=0.3)
    opts = BodyOptions(degree=1, dynamics="static", dt=1.0, gravity=(0, 0, 0),
                       pins=symmetry_pins(STRETCH))
    body = Body(mesh, mat, opts, NewtonOptions(rtol=1e-12, atol=1e-11))
    report = body.step()  # load parameter 0 -> 1 in one step
    s_ref, p11_ref = uniaxial_reference(mat, STRETCH)
    X = body.V.tabulate_dof_coordinates()
    U = body.u.x.array.reshape(-1, 3)
    lateral = np.concatenate([U[X[:, 1] > 0.25, 1] / X[X[:, 1] > 0.25, 1],
                              U[X[:, 2] > 0.25, 2] / X[X[:, 2] > 0.25, 2]]) + 1.0
    P = mat.first_piola(body.deformation_gradient())
    p11 = global_scalar(dolfinx.fem.form(P[0, 0] * body.dx))
    p22 = global_scalar(dolfinx.fem.form(P[1, 1] * body.dx))
    err_s = np.max(np.abs(lateral - s_ref)) / s_ref
    err_p = abs(p11 - p11_ref) / abs(p11_ref)
    print(f"{model}: s={lateral.mean():.12f} ref={s_ref:.12f} rel.err={err_s:.2e}; "
          f"P11={p11:.6f} ref={p11_ref:.6f} rel.err={err_p:.2e}; P22={p22:.2e}; "
          f"newton its={report.newton_iterations}")
    assert report.converged and report.min_det_f > 0
    assert err_s < 1e-6
    assert err_p < 1e-6
    assert abs(p22) < 1e-6 * abs(p11_ref)
