"""Vertex reordering (models/shell/reorder.py): round trip, invariance of the energy, locality."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from meshes.errors import InputError
from meshes.shells import icosphere, irregular_plate, perturb
from models.shell.assembly import assemble
from models.shell.bending import hinge_bending
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.hinge_angle import hinge_angle_derivatives, hinge_angles
from models.shell.membrane import edge_membrane
from models.shell.reorder import (
    VertexOrdering,
    edge_locality,
    morton_keys,
    reorder_mesh,
    vertex_ordering,
)
from models.shell.rest import RestState
from models.shell.topology import ShellTopology

METHODS = ("morton", "rcm")


def _energy(points: np.ndarray, faces: np.ndarray, h: sp.csr_matrix) -> ShellEnergy:
    """Shell energy with every term on (k_A too) and the assembled penalty."""
    topo = ShellTopology.from_faces(faces, len(points))
    rest = RestState.from_positions(topo, points)
    params = ShellParams(k_L=1e3, k_A=1e2, k_B=1e-1, k_P=1e2)
    return ShellEnergy(topo, rest, params, H=h)


def _clusters(n: int, rng: np.random.Generator) -> sp.csr_matrix:
    """Random sparse (n // 10, n) cluster matrix."""
    h = sp.random(n // 10, n, density=5.0 / n, random_state=rng, format="csr")
    return h + sp.csr_matrix((np.ones(n // 10), (np.arange(n // 10), np.arange(n // 10))),
                             shape=(n // 10, n))


@pytest.mark.parametrize("method", METHODS)
def test_round_trip(method: str, rng: np.random.Generator) -> None:
    points, faces = icosphere(3)
    new_p, new_f, order = reorder_mesh(points, faces, method)
    assert not np.array_equal(order.perm, np.arange(len(points)))  # a real permutation
    assert np.array_equal(order.perm[order.inverse], np.arange(len(points)))
    assert np.array_equal(order.to_original(new_p), points)
    values = rng.standard_normal((len(points), 3))
    assert np.array_equal(order.to_original(order.to_new(values)), values)
    # same set of oriented faces: each new face maps back to an old face, same cycle
    back = order.perm[new_f]
    key = {tuple(np.roll(f, -int(np.argmin(f)))) for f in faces.tolist()}
    assert {tuple(np.roll(f, -int(np.argmin(f)))) for f in back.tolist()} == key


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("mesh", ["sphere", "plate"])
def test_energy_invariant(method: str, mesh: str, rng: np.random.Generator) -> None:
    points, faces = icosphere(3) if mesh == "sphere" else irregular_plate(400, seed=2)
    # shuffle first so that the reordering really moves vertices
    shuffle = VertexOrdering.from_perm(rng.permutation(len(points)))
    points, faces = shuffle.to_new(points), shuffle.relabel(faces)
    h = _clusters(len(points), rng)
    x = perturb(points, 0.004, seed=3)  # well below the edge length: no face flips
    old = _energy(points, faces, h).evaluate(x, order=2)
    new_p, new_f, order = reorder_mesh(points, faces, method)
    h_new = h[:, order.perm]
    new = _energy(new_p, new_f, h_new).evaluate(order.to_new(x), order=2)
    assert abs(new.value - old.value) <= 1e-12 * abs(old.value)
    assert old.grad is not None and new.grad is not None
    g_old = old.grad.reshape(-1, 3)
    g_new = order.to_original(new.grad.reshape(-1, 3))
    assert np.linalg.norm(g_new - g_old) <= 1e-12 * np.linalg.norm(g_old)
    dof = (3 * order.perm[:, None] + np.arange(3)).ravel()  # new dof -> old dof
    h_back = sp.csr_matrix(new.hess)[np.argsort(dof)][:, np.argsort(dof)]
    diff = sp.linalg.norm(h_back - old.hess) / sp.linalg.norm(old.hess)
    assert diff <= 1e-12


def test_locality_improves_on_shuffled_and_subdivided_meshes(
        rng: np.random.Generator) -> None:
    points, faces = icosphere(5)  # midpoint subdivision order: neighbours ~n/2 apart
    mean0, band0 = edge_locality(faces)
    stats = {m: edge_locality(reorder_mesh(points, faces, m)[1]) for m in METHODS}
    print(f"icosphere(5) mean/max |i-j|: original {mean0:.1f}/{band0}, "
          + ", ".join(f"{m} {s[0]:.1f}/{s[1]}" for m, s in stats.items()))
    assert stats["morton"][0] < 0.1 * mean0
    assert stats["rcm"][0] < 0.1 * mean0 and stats["rcm"][1] < 0.1 * band0
    p, f = irregular_plate(2500, seed=1)
    shuffle = VertexOrdering.from_perm(rng.permutation(len(p)))
    ps, fs = shuffle.to_new(p), shuffle.relabel(f)
    mean_s, _ = edge_locality(fs)
    mean_m, _ = edge_locality(reorder_mesh(ps, fs, "morton")[1])
    print(f"shuffled plate mean |i-j|: {mean_s:.1f} -> morton {mean_m:.1f}")
    assert mean_m < 0.1 * mean_s


def test_morton_keys_follow_the_z_curve() -> None:
    # the 8 corners of the unit cube: key = x + 2 y + 4 z (highest bit level of each axis)
    corners = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float)
    keys = morton_keys(corners)
    assert np.array_equal(np.argsort(keys), np.arange(8))
    assert keys[7] == 2**63 - 1  # all 21 bits of all three axes set


def test_bad_input() -> None:
    points, faces = icosphere(1)
    with pytest.raises(InputError, match="method"):
        vertex_ordering(points, faces, "hilbert9")
    with pytest.raises(InputError, match="perm"):
        VertexOrdering.from_perm(np.array([0, 0, 1]))
    with pytest.raises(InputError, match="faces"):
        reorder_mesh(points, faces[:, :2])



@pytest.mark.parametrize("mode", ["exact", "gauss_newton", "projected"])
def test_fused_assembly_matches_stored_blocks(mode: str) -> None:
    """ShellEnergy scatters edge and hinge blocks inside the kernels (HessianSink); the result
    equals the stored-blocks path (term blocks, then the generic assembly)."""
    points, faces = reorder_mesh(*icosphere(3))[:2]
    topo = ShellTopology.from_faces(faces, len(points))
    rest = RestState.from_positions(topo, points)
    energy = ShellEnergy(topo, rest, ShellParams(k_L=1e3, k_B=1e-1, k_P=0.0, k_F=0.0))
    x = perturb(points, 0.02, seed=5)
    fused = energy.evaluate(x, order=2, hessian=mode).hess  # type: ignore[arg-type]
    edges = edge_membrane(x, topo.edges, rest.rest_lengths, stiffness=1e3,
                          hessian_mode=mode)  # type: ignore[arg-type]
    hinges = hinge_bending(x, topo.hinges, rest.rest_angles, 1e-1 * rest.hinge_weights,
                           hessian_mode=mode)  # type: ignore[arg-type]
    assert edges.blocks is not None and hinges.blocks is not None
    stored = assemble(energy.pattern, [(energy.pattern.maps[0], edges.blocks),
                                       (energy.pattern.maps[1], hinges.blocks)])
    assert fused is not None and fused.indptr is energy.pattern.indptr
    err = np.abs(fused.data - stored.data).max() / np.abs(stored.data).max()
    print(f"{mode}: fused vs stored max relative difference {err:.1e}")
    assert err <= 1e-14
    if mode == "projected":  # the fused projection really clamps: PSD to round-off
        assert sp.linalg.eigsh(fused, k=1, which="SA")[0][0] >= -1e-10 * abs(fused).max()


def test_value_only_path_is_bitwise_the_derivative_path() -> None:
    """The value-only hinge angle (order 0, the line search) equals the angle of the gradient
    kernel bit for bit, near flat and near +-pi folds alike."""
    points, faces = icosphere(3)
    topo = ShellTopology.from_faces(faces, len(points))
    x = perturb(points, 0.05, seed=7)
    theta, _, _ = hinge_angle_derivatives(x, topo.hinges, hessian=False)
    np.testing.assert_array_equal(hinge_angles(x, topo.hinges), theta)
    rest = RestState.from_positions(topo, points)
    energy = ShellEnergy(topo, rest, ShellParams(k_P=0.0, k_F=0.0))
    assert energy.evaluate(x, order=0).value == energy.evaluate(x, order=1).value
