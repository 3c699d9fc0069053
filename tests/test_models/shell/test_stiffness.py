"""Membrane stiffness mapping: equibiaxial / general strain against plane-stress elasticity, and
a scikit-fem P1 plane-stress cross-check of the edge membrane energy."""

from __future__ import annotations

import numpy as np
import pytest
from skfem import Basis, ElementTriP1, ElementVector, MeshTri, asm
from skfem.models.elasticity import linear_elasticity

from meshes.errors import InputError
from meshes.shells import equilateral_plate, wrap_on_cylinder
from models.shell.membrane import area_membrane, edge_membrane
from models.shell.rest import RestState
from models.shell.stiffness import (
    ShellMaterial,
    bending_stiffness,
    edge_lattice_moduli,
    membrane_stiffness,
    plate_bending_stiffness,
    shear_modulus_ratio,
    shell_stiffness,
)
from models.shell.topology import ShellTopology

LEVELS = [4, 8, 16, 32]


def _plate(nx: int, a: float) -> tuple[np.ndarray, ShellTopology, RestState]:
    p, f = equilateral_plate(nx, nx, a)
    top = ShellTopology.from_faces(f, len(p))
    return p, top, RestState.from_positions(top, p)


def _order(h: np.ndarray, err: np.ndarray) -> float:
    """Observed convergence order: slope of log err against log h (np.polyfit)."""
    return float(np.polyfit(np.log(h), np.log(err), 1)[0])


def _membrane_energy(x: np.ndarray, top: ShellTopology, rest: RestState, k_L: float,
                     k_A: float) -> float:
    value = edge_membrane(x, top.edges, rest.rest_lengths, order=0, stiffness=k_L).value
    if k_A > 0:
        value += area_membrane(x, top.faces, rest.rest_areas, order=0, stiffness=k_A).value
    return value


@pytest.mark.parametrize("nu", [1.0 / 3.0, 0.2, 0.45])
def test_equibiaxial_energy_per_area(nu: float) -> None:
    eps, rel, hs = 1e-3, [], []
    for nx in LEVELS:
        a = 1.0 / nx
        mat = ShellMaterial(E=2.0e5, nu=nu, thickness=1e-2, edge_length=a)
        k_L, k_A = membrane_stiffness(mat)
        p, top, rest = _plate(nx, a)
        w = _membrane_energy((1.0 + eps) * p, top, rest, k_L, k_A)
        continuum = mat.E * mat.thickness * eps**2 / (1.0 - nu) * rest.rest_areas.sum()
        rel.append(w / continuum - 1.0)
        hs.append(a)
        # exact discrete excess: boundary edges have one triangle, i.e. Eb / (3 F)
        assert rel[-1] == pytest.approx(top.boundary_edges.size / (3 * top.n_faces), rel=1e-9)
    order = _order(np.array(hs), np.array(rel))
    print(f"nu={nu:.3f} equibiaxial rel. excess per level {np.array(rel)}, order {order:.3f}")
    assert 0.95 <= order <= 1.05 and rel[-1] < 0.025


def _strain_energy_density(mat: ShellMaterial, eps: np.ndarray) -> float:
    """Plane-stress h (mu |eps|^2 + lambda*/2 (tr eps)^2)."""
    mu = mat.E / (2.0 * (1.0 + mat.nu))
    lam = mat.E * mat.nu / (1.0 - mat.nu**2)
    return mat.thickness * (mu * np.sum(eps * eps) + 0.5 * lam * np.trace(eps) ** 2)


@pytest.mark.parametrize("nu", [1.0 / 3.0, 0.4, 0.49])
def test_isotropic_mapping_general_strain(nu: float) -> None:
    strain = np.array([[1.0, 0.7], [0.7, -0.4]]) * 1e-6
    rel, hs = [], []
    for nx in LEVELS:
        a = 1.0 / nx
        mat = ShellMaterial(E=1.0, nu=nu, thickness=1.0, edge_length=a)
        k_L, k_A = membrane_stiffness(mat, "isotropic")
        mu_h, lam_h = edge_lattice_moduli(k_L, k_A, a)
        assert mu_h == pytest.approx(mat.E / (2 * (1 + nu)))
        assert lam_h == pytest.approx(mat.E * nu / (1 - nu**2))
        p, top, rest = _plate(nx, a)
        x = p.copy()
        x[:, :2] += p[:, :2] @ strain.T
        w = _membrane_energy(x, top, rest, k_L, k_A)
        exact = _strain_energy_density(mat, strain) * rest.rest_areas.sum()
        rel.append(abs(w / exact - 1))
        hs.append(a)
        # without the boundary edges' missing half the mapping is exact (up to O(strain))
        edges = edge_membrane(x, top.edges, rest.rest_lengths, order=0, stiffness=k_L)
        interior = w - 0.5 * edges.element_values[top.boundary_edges].sum()
        assert interior == pytest.approx(exact, rel=1e-5)
    order = _order(np.array(hs), np.array(rel))
    print(f"nu={nu:.3f} isotropic mapping rel. error per level {np.array(rel)}, order {order:.3f}")
    assert 0.9 <= order <= 1.1 and rel[-1] < 0.03


def test_mapping_limits_and_bending() -> None:
    mat = ShellMaterial(E=3.0, nu=1.0 / 3.0, thickness=0.1, edge_length=0.05)
    assert membrane_stiffness(mat, "isotropic") == pytest.approx(membrane_stiffness(mat))
    assert shear_modulus_ratio(mat) == pytest.approx(1.0)
    for nu in (0.0, 0.25, 0.5):
        m = ShellMaterial(nu=nu)
        assert shear_modulus_ratio(m) == pytest.approx((1 + nu) / (2 * (1 - nu)))
    with pytest.raises(InputError, match="nu"):
        membrane_stiffness(ShellMaterial(nu=0.2), "isotropic")
    with pytest.raises(InputError, match="thickness"):
        ShellMaterial(thickness=0.0)
    k = shell_stiffness(mat)
    assert k["k_B"] == bending_stiffness(mat) == pytest.approx(3.0 * 0.1**3 / (24 * (8 / 9)))
    assert shell_stiffness(mat, calibration="cylinder")["k_B"] == pytest.approx(k["k_B"] / 3)
    with pytest.raises(InputError, match="calibration"):
        bending_stiffness(mat, "plate")  # type: ignore[arg-type]


def _skfem_energy(p: np.ndarray, faces: np.ndarray, u: np.ndarray, mat: ShellMaterial) -> float:
    """Plane-stress P1 energy h/2 u^T K u (scikit-fem ElementVector(ElementTriP1))."""
    mesh = MeshTri(p[:, :2].T.copy(), faces.T.copy())
    basis = Basis(mesh, ElementVector(ElementTriP1()))
    lam = mat.E * mat.nu / (1.0 - mat.nu**2)
    mu = mat.E / (2.0 * (1.0 + mat.nu))
    stiff = asm(linear_elasticity(lam, mu), basis)
    vec = np.zeros(basis.N)
    vec[basis.nodal_dofs[0]] = u[:, 0]
    vec[basis.nodal_dofs[1]] = u[:, 1]
    return 0.5 * mat.thickness * float(vec @ (stiff @ vec))


def test_skfem_plane_stress_cross_check() -> None:
    """Edge springs vs P1 plane stress (nu = 1/3) for a smooth non-uniform in-plane field.

    Per interior equilateral triangle the linearised spring energy (each edge shared by two
    triangles) equals the P1 energy exactly, so the difference is the boundary edges' missing
    half: ``k_L / 2 sum_boundary (l - l0)^2 / l0`` (asserted), a boundary layer of relative size
    O(h) (fitted order asserted ~1).
    """
    delta, rel, hs = 1e-7, [], []
    for nx in LEVELS:
        a = 1.0 / nx
        mat = ShellMaterial(E=1.0, nu=1.0 / 3.0, thickness=1.0, edge_length=a)
        k_L, _ = membrane_stiffness(mat)
        p, top, rest = _plate(nx, a)
        u = np.zeros_like(p)
        u[:, 0] = delta * np.sin(np.pi * p[:, 0]) * np.cos(2.0 * p[:, 1])
        u[:, 1] = delta * np.cos(1.5 * p[:, 0] + 0.3) * np.sin(np.pi * p[:, 1])
        springs = edge_membrane(p + u, top.edges, rest.rest_lengths, order=0, stiffness=k_L)
        fem = _skfem_energy(p, top.faces, u, mat)
        boundary_half = 0.5 * springs.element_values[top.boundary_edges].sum()
        assert springs.value - fem == pytest.approx(boundary_half, rel=1e-4)
        rel.append(springs.value / fem - 1.0)
        hs.append(a)
    order = _order(np.array(hs), np.array(rel))
    print(f"skfem P1 cross-check: rel. difference per level {np.array(rel)}, order {order:.3f}")
    assert np.all(np.diff(rel) < 0) and 0.8 <= order <= 1.2


@pytest.mark.parametrize("axis", ["x", "y"])
def test_cylinder_bending_calibration(axis: str) -> None:
    """Equilateral plate rolled onto a cylinder (R = 1) about two lattice orientations.

    With k_B = D/2 ("sphere") the hinge energy tends to 3x the plate energy D/2 int R^-2 dA;
    with k_B = D/6 ("cylinder") it tends to 1 (Richardson-extrapolated, fitted order ~1 from
    the boundary hinges).
    """
    from models.shell.bending import hinge_bending

    mat = ShellMaterial(E=7.0, nu=0.3, thickness=0.02, edge_length=1.0)
    ratios, hs = [], []
    for nx in (8, 16, 32, 64):
        p, top, rest = _plate(nx, 1.0 / nx)
        q = p if axis == "x" else p[:, [1, 0, 2]]
        x = wrap_on_cylinder(q, 1.0)
        w_b = hinge_bending(x, top.hinges, rest.rest_angles, rest.hinge_weights, order=0).value
        plate = 0.5 * plate_bending_stiffness(mat) * rest.rest_areas.sum()
        ratios.append(bending_stiffness(mat, "cylinder") * w_b / plate)
        hs.append(1.0 / nx)
    ratios_a = np.array(ratios)
    order = _order(np.array(hs), np.abs(ratios_a - 1.0))
    limit = 2.0 * ratios_a[-1] - ratios_a[-2]  # Richardson for order 1
    sphere_limit = limit * bending_stiffness(mat) / bending_stiffness(mat, "cylinder")
    print(f"cylinder about {axis}: ratio (cylinder calibration) per level {ratios_a}, "
          f"order {order:.3f}, Richardson limit {limit:.5f}; 'sphere' calibration -> "
          f"{sphere_limit:.4f}")
    assert 0.9 <= order <= 1.1 and abs(limit - 1.0) < 2e-3
    assert sphere_limit == pytest.approx(3.0, rel=2e-3)
