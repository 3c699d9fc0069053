"""Patch energies are exact blocks of the global W: gradients, Hessians, energies, rest data."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.shells import icosphere
from models.embedding.clusters import ClusterOptions, build_clusters
from models.shell.energy import ShellParams
from models.shell.rest import RestState
from models.shell.topology import ShellTopology
from solvers.decomposition.patch_energy import PatchEnergy, ShellProblem
from solvers.decomposition.patches import build_patches


@pytest.fixture(scope="module")
def sphere_case() -> tuple[ShellProblem, list[PatchEnergy], np.ndarray]:
    """Curved rest shell (theta0 != 0), area term on, 24 clusters, 4 patches, random state."""
    pts, faces = icosphere(3)
    topo = ShellTopology.from_faces(faces, len(pts))
    clusters = build_clusters(pts, faces, ClusterOptions(count=24))
    rng = np.random.default_rng(7)
    target = 0.97 * pts
    problem = ShellProblem(topo, RestState.from_positions(topo, pts),
                           ShellParams(k_L=1e3, k_A=50.0, k_B=1e-1, k_P=1e3),
                           clusters.H.tocsr(), target)
    patches = build_patches(topo, clusters.partition, 4)
    energies = [PatchEnergy(problem, p.interior) for p in patches.patches]
    x = pts + 0.01 * rng.standard_normal(pts.shape)
    return problem, energies, x


def _dofs(vertices: np.ndarray) -> np.ndarray:
    return (3 * vertices[:, None] + np.arange(3)).reshape(-1)


def test_patch_gradients_and_hessians_are_global_blocks(sphere_case) -> None:
    problem, energies, x = sphere_case
    ev = problem.energy().evaluate(x)
    grad = np.zeros_like(ev.grad)
    worst_h = 0.0
    for pe in energies:
        pe.set_state(x)
        local = pe.evaluate(x[pe.interior])
        grad[_dofs(pe.interior)] = local.grad
        block = ev.hess[_dofs(pe.interior)][:, _dofs(pe.interior)]
        worst_h = max(worst_h, abs(block - local.hess).max() / abs(block).max())
    err_g = np.abs(grad - ev.grad).max() / np.abs(ev.grad).max()
    print(f"max rel gradient error {err_g:.2e}, Hessian block error {worst_h:.2e}")
    assert err_g < 1e-12
    assert worst_h < 1e-12


def test_owned_energies_sum_to_w(sphere_case) -> None:
    problem, energies, x = sphere_case
    w = problem.energy().value(x)
    total = 0.0
    for pe in energies:
        pe.set_state(x)
        total += pe.owned_energy()
    print(f"W = {w:.15e}, sum of owned = {total:.15e}")
    assert abs(total - w) <= 1e-13 * abs(w)


def test_owned_energies_include_the_flip_barrier(sphere_case) -> None:
    """A face squashed into the barrier's active zone: the owned sums (order 0 and from an
    order-2 evaluation's elements) still add up to W, barrier included."""
    problem, energies, x = sphere_case
    y = x.copy()
    f = problem.topology.faces[len(problem.topology.faces) // 2]
    mid = 0.5 * (y[f[0]] + y[f[1]])
    y[f[2]] = mid + 0.05 * (y[f[2]] - mid)
    ev = problem.energy().evaluate(y, order=0)
    assert ev.terms["flip_barrier"] > 1e-6 * abs(ev.value)
    order0 = from_elements = 0.0
    for pe in energies:
        pe.set_state(y)
        order0 += pe.owned_energy()
        from_elements += pe.owned_energy(pe.energy.evaluate(y[pe.local], order=2).elements)
    print(f"W = {ev.value:.15e} (barrier {ev.terms['flip_barrier']:.3e}), owned {order0:.15e}")
    assert abs(order0 - ev.value) <= 1e-13 * abs(ev.value)
    assert abs(from_elements - ev.value) <= 1e-13 * abs(ev.value)


def test_patches_take_their_hinges_references_from_the_global_ones(sphere_case) -> None:
    """Hinge references a turn off on every seventh hinge (``theta + 2 pi``; without the fold
    contact, which would read those hinges as folds closed through themselves): the patches'
    owned energies, each patch given its slice of the global references, still add up to the
    global W with the same references, which differs from W without them."""
    from dataclasses import replace

    from models.shell.hinge_angle import hinge_angles

    problem, contact_energies, x = sphere_case
    problem = replace(problem, params=replace(problem.params, fold_contact=0.0))
    energies = [PatchEnergy(problem, pe.interior) for pe in contact_energies]
    theta = hinge_angles(x, problem.topology.hinges)
    branch = theta.copy()
    branch[::7] += 2 * np.pi
    glob = problem.energy()
    plain = glob.value(x)
    glob.set_hinge_branch(branch)
    w = glob.value(x)
    total = 0.0
    for pe in energies:
        pe.set_state(x)
        pe.set_hinge_branch(branch)
        total += pe.owned_energy()
        pe.set_hinge_branch(None)
    print(f"W with references {w:.15e} (without {plain:.6e}), sum of owned {total:.15e}")
    assert w > 1.5 * plain
    assert abs(total - w) <= 1e-13 * abs(w)


def test_sliced_rest_equals_recomputed(sphere_case) -> None:
    problem, energies, _ = sphere_case
    for pe in energies:
        e = pe.energy
        fresh = RestState.from_positions(e.topology, e.rest.positions)
        assert np.abs(e.rest.rest_angles).max() > 1e-2  # curved rest shell
        np.testing.assert_allclose(e.rest.rest_angles, fresh.rest_angles, rtol=0, atol=1e-13)
        np.testing.assert_allclose(e.rest.hinge_weights, fresh.hinge_weights, rtol=1e-13)
        np.testing.assert_allclose(e.rest.rest_lengths, fresh.rest_lengths, rtol=1e-14)
        np.testing.assert_allclose(e.rest.rest_areas, fresh.rest_areas, rtol=1e-14)


def test_patch_taylor(sphere_case) -> None:
    """W(x + h d) - W - h g.d = O(h^2), g(x + h d) - g - h A d = O(h^2) (fitted slopes)."""
    _, energies, x = sphere_case
    pe = energies[1]
    pe.set_state(x)
    x0 = x[pe.interior]
    d = np.random.default_rng(3).standard_normal(x0.shape) * 1e-2
    ev = pe.evaluate(x0)
    hs = 2.0 ** -np.arange(4, 10)
    r0 = [abs(pe.value(x0 + h * d) - ev.value - h * ev.grad @ d.ravel()) for h in hs]
    r1 = [np.linalg.norm(pe.evaluate(x0 + h * d, order=1).grad - ev.grad
                         - h * (ev.hess @ d.ravel())) for h in hs]
    s0, s1 = np.polyfit(np.log(hs), np.log(r0), 1)[0], np.polyfit(np.log(hs), np.log(r1), 1)[0]
    print(f"Taylor slopes: energy {s0:.3f}, gradient {s1:.3f}")
    assert abs(s0 - 2) < 0.1
    assert abs(s1 - 2) < 0.1
