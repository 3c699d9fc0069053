"""Rest state, rigid-motion invariance, symmetry and Hessian modes of the membrane terms and of
the composite ShellEnergy (membrane + area + bending + penalty)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from meshes.errors import InputError
from meshes.shells import perturb
from models.shell.assembly import project_psd_blocks
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.membrane import area_membrane, edge_membrane
from models.shell.rest import RestState
from validation.taylor import EPS, dense_sym_eigs, random_shell, remainders, slope

TERMS = {
    "edge": (edge_membrane, lambda t: t.edges, lambda r: r.rest_lengths),
    "area": (area_membrane, lambda t: t.faces, lambda r: r.rest_areas),
}


def _cluster_matrix(p: np.ndarray, c: int, seed: int) -> sp.csr_matrix:
    """Gaussian cluster weights around c random vertices (rows sum to 1), truncated at 2 sigma."""
    rng = np.random.default_rng(seed)
    centres = p[rng.choice(len(p), c, replace=False)]
    d2 = ((centres[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    sigma2 = np.median(d2) / 4
    w = np.where(d2 < 4 * sigma2, np.exp(-d2 / (2 * sigma2)), 0.0)
    return sp.csr_matrix(w / w.sum(axis=1, keepdims=True))


def _energy(kind: str, **kw: object) -> tuple[np.ndarray, ShellEnergy]:
    p, top, rest = random_shell(kind)
    params = ShellParams(**{"k_L": 3.0, "k_A": 2.0, "k_B": 0.5, "k_P": 5.0, **kw})
    return p, ShellEnergy(top, rest, params, H=_cluster_matrix(p, 8, 4))


@pytest.mark.parametrize("name", list(TERMS))
@pytest.mark.parametrize("kind", ["plate", "sphere"])
def test_zero_at_rest_and_rigid_invariance(name: str, kind: str) -> None:
    term, st, rl = TERMS[name]
    p, top, rest = random_shell(kind)
    ev0 = term(p, st(top), rl(rest))
    assert abs(ev0.value) < 1e-28 and np.abs(ev0.grad).max() < 1e-13
    x = perturb(p, 0.05, 3)
    rot = Rotation.random(random_state=5).as_matrix()
    y = x @ rot.T + np.array([0.3, -1.2, 2.0])
    ev, evr = term(x, st(top), rl(rest)), term(y, st(top), rl(rest))
    assert evr.value == pytest.approx(ev.value, rel=1e-12)
    np.testing.assert_allclose(evr.grad.reshape(-1, 3), ev.grad.reshape(-1, 3) @ rot.T,
                               atol=1e-12 * np.abs(ev.grad).max())


def _compressed(kind: str) -> tuple[np.ndarray, ShellEnergy]:
    """Energy with everything on, at a state compressed by 10 % in x and randomly perturbed."""
    p, energy = _energy(kind)
    return perturb(p * np.array([0.9, 1.0, 1.0]), 0.01, 6), energy


@pytest.mark.parametrize("kind", ["plate", "sphere", "thin"])
def test_composite_modes_symmetric_and_psd(kind: str) -> None:
    x, energy = _compressed(kind)
    h_exact = energy.evaluate(x, hessian="exact").hess
    lam_exact = dense_sym_eigs(h_exact)
    scale = np.abs(lam_exact).max()
    print(f"{kind}: exact Hessian min eig / max |eig| = {lam_exact.min() / scale:.3e}")
    assert lam_exact.min() < -1e-6 * scale  # compression makes the exact Hessian indefinite
    for mode in ("exact", "gauss_newton", "projected"):
        h = energy.evaluate(x, hessian=mode).hess
        assert abs(h - h.T).max() <= 1e-13 * scale
        if mode != "exact":
            lam = dense_sym_eigs(h)
            print(f"{kind} {mode}: min eig / scale = {lam.min() / scale:.3e}")
            assert lam.min() >= -1e-10 * scale


@pytest.mark.parametrize("name", list(TERMS))
def test_term_modes_psd_per_block(name: str) -> None:
    term, st, rl = TERMS[name]
    p, top, rest = random_shell("plate")
    x = perturb(p * np.array([0.85, 1.0, 1.0]), 0.01, 2)
    exact = term(x, st(top), rl(rest), hessian_mode="exact").blocks
    assert np.linalg.eigvalsh(exact).min() < 0
    projected = exact.copy()
    project_psd_blocks(projected)
    for mode in ("gauss_newton", "projected"):
        blocks = term(x, st(top), rl(rest), hessian_mode=mode).blocks
        lam = np.linalg.eigvalsh(blocks)
        assert lam.min() >= -1e-10 * np.abs(lam).max()
    # edges: the closed-form clamp equals the generic eigenvalue projection
    if name == "edge":
        got = term(x, st(top), rl(rest), hessian_mode="projected").blocks
        np.testing.assert_allclose(got, projected, atol=1e-12 * np.abs(exact).max())


@pytest.mark.parametrize("penalty_hessian", ["assembled", "low_rank"])
def test_composite_taylor(penalty_hessian: str, rng: np.random.Generator) -> None:
    p, energy = _energy("plate", penalty_hessian=penalty_hessian)
    energy.set_target(perturb(p, 0.02, 11))

    def f(v: np.ndarray) -> tuple[float, np.ndarray, sp.csr_matrix]:
        ev = energy.evaluate(v, hessian="exact")
        g = ev.penalty_factor
        return ev.value, ev.grad, ev.hess if g is None else ev.hess + g.T @ g

    x = perturb(p, 0.03, 12).reshape(-1)
    r1, r2, r3 = remainders(f, x, rng.standard_normal(x.size) * 0.01)
    s1, s2, s3 = slope(EPS, r1), slope(EPS, r2), slope(EPS[:4], r3[:4])
    print(f"composite {penalty_hessian}: slopes {s1:.3f} {s2:.3f} {s3:.3f}")
    assert 1.9 <= s1 <= 2.1 and 1.9 <= s2 <= 2.1 and 2.8 <= s3 <= 3.2


def test_low_rank_equals_assembled() -> None:
    p, e_asm = _energy("sphere")
    _, e_low = _energy("sphere", penalty_hessian="low_rank")
    y = perturb(p, 0.02, 13)
    e_asm.set_target(y)
    e_low.set_target(y)
    x = perturb(p, 0.03, 14)
    a, b = e_asm.evaluate(x), e_low.evaluate(x)
    assert a.penalty_factor is None and b.penalty_factor is not None
    full = b.hess + b.penalty_factor.T @ b.penalty_factor
    assert abs(a.hess - full).max() <= 1e-12 * abs(a.hess).max()
    assert a.value == b.value and np.array_equal(a.grad, b.grad)
    gram = e_asm.penalty_gram()
    k_p = e_asm.params.k_P
    assert abs(b.penalty_factor.T @ b.penalty_factor
               - 2 * k_p * sp.kron(gram, sp.identity(3))).max() < 1e-12 * k_p


def test_composite_zero_at_rest_and_terms() -> None:
    p, energy = _energy("sphere")
    ev = energy.evaluate(p)
    assert ev.value < 1e-25 and np.abs(ev.grad).max() < 1e-12
    assert set(ev.terms) == {"membrane_edge", "membrane_area", "bending", "penalty", "flip_barrier"}
    x = perturb(p, 0.02, 1)
    ev = energy.evaluate(x)
    assert ev.value == pytest.approx(sum(ev.terms.values()), rel=1e-14)
    assert energy.value(x) == ev.value


def test_zero_stiffness_terms_are_skipped() -> None:
    p, top, rest = random_shell("plate")
    full = ShellEnergy(top, rest, ShellParams(k_L=1.0, k_A=1.0, k_B=1.0, k_P=0.0))
    only_edges = ShellEnergy(top, rest, ShellParams(k_L=1.0, k_A=0.0, k_B=0.0, k_P=0.0, k_F=0.0))
    x = perturb(p, 0.05, 2)
    assert set(only_edges.evaluate(x).terms) == {"membrane_edge"}
    # edges alone: blocks = n diagonal + 2 per edge; hinges add their new (k, l) pairs
    assert only_edges.pattern.n_blocks == top.n_vertices + 2 * top.n_edges
    kl = {tuple(sorted(h)) for h in top.hinges[:, 2:].tolist()}
    new_pairs = kl - {tuple(e) for e in top.edges.tolist()}
    assert full.pattern.n_blocks == top.n_vertices + 2 * top.n_edges + 2 * len(new_pairs)
    assert only_edges.evaluate(x).value == pytest.approx(full.evaluate(x).terms["membrane_edge"])


def test_bending_density_sums_to_bending_energy() -> None:
    p, energy = _energy("sphere")
    x = perturb(p, 0.03, 3)
    rho = energy.bending_density(x)
    total = float(rho @ energy.rest.vertex_areas)
    assert total == pytest.approx(energy.evaluate(x, order=0).terms["bending"], rel=1e-12)


def test_input_errors() -> None:
    p, top, rest = random_shell("plate")
    with pytest.raises(InputError, match="k_L"):
        ShellParams(k_L=-1.0)
    with pytest.raises(InputError, match="hessian_mode"):
        ShellParams(hessian_mode="newton")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="penalty_hessian"):
        ShellParams(penalty_hessian="dense")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="H"):
        ShellEnergy(top, rest, ShellParams(k_P=1.0))
    with pytest.raises(InputError, match="H"):
        ShellEnergy(top, rest, ShellParams(k_P=1.0), H=sp.identity(top.n_vertices + 1))
    energy = ShellEnergy(top, rest, ShellParams(k_P=0.0))
    with pytest.raises(InputError, match="x"):
        energy.evaluate(p[:-1])
    bad = p.copy()
    bad[top.faces[3, 2]] = 0.5 * (bad[top.faces[3, 0]] + bad[top.faces[3, 1]])
    with pytest.raises(InputError, match="face 3"):
        RestState.from_positions(top, bad)


@pytest.mark.parametrize("name", ["area", "bending"])
def test_reduced_projection_equals_full_clamp(name: str) -> None:
    """The translation-reduced clamp equals V max(w, 0) V^T of the full block (numpy eigh)."""
    from models.shell.bending import hinge_bending

    p, top, rest = random_shell("sphere")
    x = perturb(p, 0.05, 4)
    if name == "area":
        blocks = area_membrane(x, top.faces, rest.rest_areas).blocks
    else:
        blocks = hinge_bending(x, top.hinges, rest.rest_angles, rest.hinge_weights).blocks
    w, v = np.linalg.eigh(blocks)
    reference = np.einsum("tij,tj,tkj->tik", v, np.maximum(w, 0.0), v)
    reduced, full = blocks.copy(), blocks.copy()
    project_psd_blocks(reduced)
    project_psd_blocks(full, translation_invariant=False)
    scale = np.abs(blocks).max()
    assert (w[:, 0] < -1e-8 * scale).mean() > 0.2  # many blocks really are indefinite
    np.testing.assert_allclose(reduced, reference, atol=1e-12 * scale)
    np.testing.assert_allclose(full, reference, atol=1e-12 * scale)


def test_collapsed_edges_and_faces_stay_finite() -> None:
    """Coincident vertices / a flattened face give finite values, gradients and Hessians."""
    p, top, rest = random_shell("plate")
    x = p.copy()
    i, j = top.edges[5]
    x[j] = x[i]  # edge 5 collapsed to a point
    far = np.flatnonzero(~np.isin(top.faces, [i, j]).any(axis=1))[0]
    f = top.faces[far]
    x[f[2]] = 0.5 * (x[f[0]] + x[f[1]])  # face `far` flattened onto a line
    for term, st, rl in TERMS.values():
        for mode in ("exact", "gauss_newton", "projected"):
            ev = term(x, st(top), rl(rest), hessian_mode=mode)
            assert np.isfinite(ev.value) and np.all(np.isfinite(ev.grad))
            assert np.all(np.isfinite(ev.blocks))
    edge = edge_membrane(x, top.edges, rest.rest_lengths).element_values[5]
    assert edge == pytest.approx(rest.rest_lengths[5], rel=1e-9)  # (0 - l0)^2 / l0
    area = area_membrane(x, top.faces, rest.rest_areas).element_values[far]
    assert area == pytest.approx(rest.rest_areas[far], rel=1e-9)  # (0 - A0)^2 / A0


def test_the_energy_follows_a_closing_fold_from_solve_start_to_solve_start() -> None:
    """``follow_hinges`` takes each hinge angle on the branch nearest to the last reference:
    a fold closed in steps of 0.3 rad (below pi each) from a bend angle of 2.6 to 3.5 rad ends
    on the reference 3.5 (not 3.5 - 2 pi), and W_B is ``k_B w theta^2`` there (no fold
    contact); the references are checkpointable (copy out, set back; a wrong shape refused
    naming them). With the fold contact on, that state is a fold closed through itself:
    +inf, and its hinge's four vertices are the blocked ones; ``release_folds`` gives that
    hinge its principal angle as reference and the state is finite again."""
    from models.shell.hinge_angle import hinge_angles
    from models.shell.topology import ShellTopology

    def fold(theta: float) -> np.ndarray:
        c, s = np.cos(theta / 2), np.sin(theta / 2)
        return np.array([[0.0, 0, 0], [1, 0, 0], [0.7, c, -s], [0.3, -c, -s]])

    topo = ShellTopology.from_faces(np.array([[0, 1, 2], [1, 0, 3]]), 4)
    rest = RestState.from_positions(topo, fold(0.0))
    energy = ShellEnergy(topo, rest, ShellParams(k_L=0.0, k_B=2.0, k_P=0.0, k_F=0.0,
                                                 fold_contact=0.0))
    assert energy.hinge_branch is None
    for theta in (2.6, 2.9, 3.2, 3.5):
        energy.follow_hinges(fold(theta))
    branch = energy.hinge_branch
    assert branch is not None
    assert branch[0] == pytest.approx(3.5, abs=1e-12)
    assert hinge_angles(fold(3.5), topo.hinges)[0] == pytest.approx(3.5 - 2 * np.pi, abs=1e-12)
    w = 2.0 * rest.hinge_weights[0]
    assert energy.value(fold(3.5)) == pytest.approx(w * 3.5 ** 2, rel=1e-12)
    energy.set_hinge_branch(None)
    assert energy.value(fold(3.5)) == pytest.approx(w * (3.5 - 2 * np.pi) ** 2, rel=1e-12)
    energy.set_hinge_branch(branch)
    assert energy.value(fold(3.5)) == pytest.approx(w * 3.5 ** 2, rel=1e-12)
    with pytest.raises(InputError, match="hinge branch"):
        energy.set_hinge_branch(np.zeros(3))
    assert energy.blocked_vertices(fold(3.5)).size == 0  # no contact: nothing blocked
    touching = ShellEnergy(topo, rest, ShellParams(k_L=0.0, k_B=2.0, k_P=0.0, k_F=0.0))
    touching.set_hinge_branch(branch)
    assert touching.value(fold(3.5)) == np.inf
    assert np.array_equal(touching.blocked_vertices(fold(3.5)), [0, 1, 2, 3])
    assert touching.blocked_vertices(fold(3.0)).size == 0
    with pytest.raises(InputError, match="fold_gap"):
        ShellParams(fold_gap=4.0)
    # release_folds: the closed hinge takes its principal angle, open again on that side
    assert energy.release_folds(fold(3.5)) == 0  # no fold contact: nothing closed
    assert touching.release_folds(fold(3.0)) == 0
    assert touching.hinge_branch[0] == branch[0]  # an open fold keeps its reference
    assert touching.release_folds(fold(3.5)) == 1
    assert touching.hinge_branch[0] == pytest.approx(3.5 - 2 * np.pi, abs=1e-12)
    assert touching.blocked_vertices(fold(3.5)).size == 0
    assert touching.value(fold(3.5)) < np.inf
    fresh = ShellEnergy(topo, rest, ShellParams(k_L=0.0, k_B=2.0, k_P=0.0, k_F=0.0))
    assert fresh.release_folds(fold(3.5)) == 0 and fresh.hinge_branch is None  # no reference
