"""Cross-check of the total strain energy against an independent scikit-fem implementation."""

from __future__ import annotations

import numpy as np
import pytest
from skfem import Basis, ElementTetP1, ElementVector, Functional, MeshTet
from skfem.helpers import det, grad

from models.backend import MPI, dolfinx, global_scalar, ufl, vector_space
from models.materials import Material


def displacement(x: np.ndarray) -> np.ndarray:
    """A nonlinear field (strains ~ 20 %), rows = components, columns = points."""
    return np.array([0.1 * np.sin(2.0 * x[0]) * x[1] + 0.05 * x[2],
                     0.15 * x[0] * x[2] ** 2,
                     -0.1 * np.cos(x[1]) * x[2] + 0.08 * x[0] * x[1]])


def skfem_energy(points: np.ndarray, tets: np.ndarray, mat: Material) -> float:
    """int psi(F) with F = I + grad u, u the P1 interpolant, written directly in numpy."""
    mesh = MeshTet(points.T.copy(), tets.T.copy())
    basis = Basis(mesh, ElementVector(ElementTetP1()), intorder=2)
    nodal = displacement(mesh.p)
    u = np.zeros(basis.N)
    for k in range(3):
        u[basis.nodal_dofs[k]] = nodal[k]
    mu, lam = mat.mu, mat.lmbda
    eye = np.eye(3)[:, :, None, None]

    @Functional
    def energy(w):
        F = eye + grad(w["u"])
        if mat.model == "neo_hookean":
            J = det(F)
            return (0.5 * mu * (np.einsum("ij...,ij...->...", F, F) - 3.0)
                    - mu * np.log(J) + 0.5 * lam * np.log(J) ** 2)
        E = 0.5 * (np.einsum("ki...,kj...->ij...", F, F) - eye)
        trE = np.einsum("ii...->...", E)
        return 0.5 * lam * trE**2 + mu * np.einsum("ij...,ij...->...", E, E)

    return float(energy.assemble(basis, u=basis.interpolate(u)))


@pytest.mark.parametrize("model", ["neo_hookean", "stvk"])
def test_strain_energy_matches_scikit_fem(model):
    mesh = dolfinx.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1.0, 0.7, 0.5]], [4, 3, 2],
                                   dolfinx.mesh.CellType.tetrahedron)
    mat = Material(model=model, E=3.0e5, nu=0.4)
    V = vector_space(mesh, 1)
    u = dolfinx.fem.Function(V)
    u.interpolate(displacement)
    F = ufl.Identity(3) + ufl.grad(u)
    ours = global_scalar(dolfinx.fem.form(mat.psi(F) * ufl.dx(metadata={"quadrature_degree": 2})))
    points = mesh.geometry.x
    tets = mesh.geometry.dofmaps[0]
    theirs = skfem_energy(points, tets, mat)
    rel = abs(ours - theirs) / abs(theirs)
    print(f"{model}: dolfinx {ours:.15e} scikit-fem {theirs:.15e} rel.diff {rel:.2e}")
    assert ours > 1.0  # a real deformation, not a trivial zero
    assert rel < 1e-10
