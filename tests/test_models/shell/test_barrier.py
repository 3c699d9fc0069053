"""The shell's flip barrier W_F (models/shell/barrier.py): Taylor tests, closed-form values, zero
at rest, rotation invariance with the target, Hessian modes, and no change to a wrinkled plate
whose faces stay above the activation ratio (issue 8)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from meshes.errors import InputError
from meshes.shells import grid_plate
from models.embedding.clusters import ClusterOptions, build_clusters
from models.shell.barrier import (
    barrier_weights,
    flip_barrier,
    reference_normals,
    signed_area_ratio,
)
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState, face_quality
from models.shell.topology import ShellTopology
from solvers.shell_newton import ShellNewtonOptions, minimize
from validation.taylor import EPS, random_shell, remainders, slope, term_oracle

S_HAT = 0.1


def squashed(kind: str, factor: float, seed: int = 3) -> tuple[np.ndarray, ShellTopology,
                                                                 RestState, np.ndarray]:
    """Rest shell ``kind``, positions with x scaled by ``factor`` (s ~ factor) and a small
    random perturbation; also returns the unit rest normals (the reference)."""
    p, top, rest = random_shell(kind)
    x = p * np.array([factor, 1.0, 1.0])
    x = x + 0.02 * factor * rest.rest_lengths.min() * \
        np.random.default_rng(seed).standard_normal(x.shape)
    ref = reference_normals(p, top.faces, rest.rest_areas, np.zeros((top.n_faces, 3)))
    return x, top, rest, ref


def barrier_oracle(top: ShellTopology, rest: RestState, ref: np.ndarray, **kw: object):  # noqa: ANN201
    weights = barrier_weights(rest.positions, top.faces)
    return term_oracle(flip_barrier, top.faces, top.n_vertices, rest_area=rest.rest_areas,
                       weight=weights, ref=ref, s_hat=S_HAT, **kw)


@pytest.mark.parametrize("kind", ["plate", "thin"])
def test_flip_barrier_taylor(kind: str, rng: np.random.Generator) -> None:
    """Every face active (s ~ 0.05 < s_hat): value/gradient remainders O(eps^2), O(eps^3)."""
    x, top, rest, ref = squashed(kind, 0.05)
    d = rng.standard_normal(x.size)
    eps = EPS * 0.05 * rest.rest_lengths.min()
    for e in (0.0, eps.max()):
        s = signed_area_ratio((x.reshape(-1) + e * d).reshape(-1, 3), top.faces,
                              rest.rest_areas, ref)
        assert 0.0 < s.min() and s.max() < S_HAT, (s.min(), s.max())  # all active, none flipped
    f = barrier_oracle(top, rest, ref, stiffness=3.0)
    r1, r2, r3 = remainders(f, x.reshape(-1), d, eps)
    s1, s2, s3 = slope(eps, r1), slope(eps, r2), slope(eps[:4], r3[:4])
    print(f"flip barrier {kind}: slopes value {s1:.3f} grad {s2:.3f} order-3 {s3:.3f}")
    assert 1.9 <= s1 <= 2.1 and 1.9 <= s2 <= 2.1 and 2.8 <= s3 <= 3.2


def test_flip_barrier_closed_form_and_switching() -> None:
    """Unit equilateral triangle in the xy plane with x scaled by c: s = c and
    W = k A0 (-(c - s_hat)^2 ln(c / s_hat)); zero (value, gradient, Hessian) for c >= s_hat;
    +inf for c <= 0."""
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(3.0) / 2, 0.0]])
    faces = np.array([[0, 1, 2]])
    a0 = np.array([np.sqrt(3.0) / 4])
    w = barrier_weights(p, faces)
    assert w[0] == pytest.approx(a0[0], rel=1e-14)  # equilateral: A0 / q = A0
    ref = np.array([[0.0, 0.0, 1.0]])
    k = 5.0
    for c in (0.01, 0.05, 0.099):
        x = p * np.array([c, 1.0, 1.0])
        ev = flip_barrier(x, faces, a0, w, ref, s_hat=S_HAT, stiffness=k)
        assert signed_area_ratio(x, faces, a0, ref)[0] == pytest.approx(c, rel=1e-14)
        assert ev.value == pytest.approx(-k * a0[0] * (c - S_HAT) ** 2 * np.log(c / S_HAT),
                                         rel=1e-13)
        assert ev.value > 0 and np.abs(ev.grad).max() > 0
    for c in (0.1, 0.5, 1.0):
        ev = flip_barrier(p * np.array([c, 1.0, 1.0]), faces, a0, w, ref, s_hat=S_HAT)
        assert ev.value == 0.0 and not ev.grad.any() and ev.blocks is None
    for c in (0.0, -0.3):
        ev = flip_barrier(p * np.array([c, 1.0, 1.0]), faces, a0, w, ref, s_hat=S_HAT)
        assert ev.value == np.inf and np.all(np.isfinite(ev.grad))
    with pytest.raises(InputError, match="s_hat"):
        flip_barrier(p, faces, a0, w, ref, s_hat=0.0)
    with pytest.raises(InputError, match="flip_activation"):
        ShellParams(flip_activation=1.5)
    with pytest.raises(InputError, match="k_F"):
        ShellParams(k_F=-1.0)
    with pytest.raises(InputError, match="flip_quality"):
        ShellParams(flip_quality=-0.1)


def test_flip_quality_selects_the_faces() -> None:
    """Default ``flip_quality = 1``: every face; 0.5: the irregular plate's one face of quality
    0.448 and every face of the 'thin' shell; on the icosphere (q >= 0.977) no face, hence no
    barrier term at all (the draft's energy)."""
    for kind, covered in (("plate", 1), ("thin", None), ("sphere", 0)):
        p, top, rest = random_shell(kind)
        q = face_quality(p, top.faces)
        assert ShellEnergy(top, rest, ShellParams(k_P=0.0)).flip_faces.size == top.n_faces
        energy = ShellEnergy(top, rest, ShellParams(k_P=0.0, flip_quality=0.5))
        np.testing.assert_array_equal(energy.flip_faces, np.flatnonzero(q < 0.5))
        assert energy.flip_faces.size == (top.n_faces if covered is None else covered)
        assert ("flip_barrier" in energy.evaluate(p, order=0).terms) == (covered != 0)


def test_barrier_weights_boost_slivers() -> None:
    """w = A0 / q: a sliver of quality q is weighted 1 / q times its own area."""
    p, top, rest = random_shell("thin")
    q = face_quality(p, top.faces)
    np.testing.assert_allclose(barrier_weights(p, top.faces), rest.rest_areas / q, rtol=1e-12)
    assert q.min() < 1e-2  # the 'thin' shell has slivers


@pytest.mark.parametrize("mode", ["exact", "gauss_newton", "projected"])
def test_flip_barrier_hessian_modes(mode: str) -> None:
    """Blocks symmetric; Gauss-Newton and projected blocks PSD; exact blocks indefinite (the
    skew ``b' d2s`` part); the three agree on ``b'' grad s grad s^T`` along grad s."""
    x, top, rest, ref = squashed("plate", 0.05)
    w = barrier_weights(rest.positions, top.faces)
    ev = flip_barrier(x, top.faces, rest.rest_areas, w, ref, s_hat=S_HAT, hessian_mode=mode)
    blocks = ev.blocks
    assert np.abs(blocks - blocks.transpose(0, 2, 1)).max() <= 1e-12 * np.abs(blocks).max()
    low = np.linalg.eigvalsh(blocks).min(axis=1) / np.abs(blocks).max(axis=(1, 2))
    print(f"{mode}: smallest relative eigenvalue of a block {low.min():.3e}")
    if mode == "exact":
        assert low.min() < -1e-3
    else:
        assert low.min() >= -1e-12


def test_zero_at_rest_and_rotation_invariant() -> None:
    """The default shell energy (barrier on) is zero with zero gradient at rest; rotating the
    positions and the target together leaves the barrier energy and s unchanged."""
    p, top, rest = random_shell("sphere")
    energy = ShellEnergy(top, rest, ShellParams(k_P=0.0, flip_quality=1.0))
    ev = energy.evaluate(p)
    assert "flip_barrier" in ev.terms and ev.terms["flip_barrier"] == 0.0
    assert ev.value == pytest.approx(0.0, abs=1e-20) and np.abs(ev.grad).max() <= 1e-12
    only = ShellEnergy(top, rest, ShellParams(k_L=0.0, k_B=0.0, k_P=0.0, k_F=2.0,
                                              flip_quality=1.0))
    x = p * np.array([0.06, 1.0, 1.0])  # faces squashed along x: some of them active
    base = only.evaluate(x, order=1)
    assert base.value > 0
    rot = Rotation.from_rotvec([0.4, -1.9, 0.7]).as_matrix()
    only.set_target(p @ rot.T)
    turned = only.evaluate(x @ rot.T, order=1)
    assert turned.value == pytest.approx(base.value, rel=1e-12)
    np.testing.assert_allclose(turned.grad.reshape(-1, 3), base.grad.reshape(-1, 3) @ rot.T,
                               atol=1e-10 * np.abs(base.grad).max())
    # without moving the reference, the same rotation (by 111 degrees) turns faces over
    only.set_target(p)
    assert only.value(x @ rot.T) == np.inf


def wrinkled_plate(compression: float, **params: float) -> tuple[float, float, int]:
    """The 20x20 plate of test_shell_solver_wrinkles compressed along x and solved exactly:
    ``(W, min s, iterations)``."""
    pts, faces = grid_plate(20, 20, 1.0, 1.0)
    topo = ShellTopology.from_faces(faces, len(pts))
    clusters = build_clusters(pts, faces, ClusterOptions(count=20))
    shell = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, penalty_hessian="low_rank", **params)
    energy = ShellEnergy(topo, RestState.from_positions(topo, pts), shell, H=clusters.H)
    y = pts.copy()
    y[:, 0] = 0.5 + (1.0 - compression) * (pts[:, 0] - 0.5)
    energy.set_target(y)
    x0 = y.copy()
    x0[:, 2] += 1e-4 * np.random.default_rng(1).standard_normal(len(y))
    x, report = minimize(energy, x0, ShellNewtonOptions(rtol=1e-9, max_iterations=300))
    assert report.converged
    s = signed_area_ratio(x, faces, energy.rest.rest_areas, energy.reference_normals)
    return report.energy, float(s.min()), report.iterations


def test_barrier_leaves_wrinkles_unchanged() -> None:
    """35 % compression: the folds tilt faces down to s = 0.179 (measured), above the default
    activation 0.1, so the wrinkled energy is the same with the barrier off or on every face
    (measured 30.631943380089 both); activation 0.5 would change it (measured 31.4459: +2.7 %)."""
    w_off, s_off, it_off = wrinkled_plate(0.35, k_F=0.0)
    w_on, s_on, it_on = wrinkled_plate(0.35)
    w_half, s_half, _ = wrinkled_plate(0.35, flip_activation=0.5)
    print(f"W off {w_off:.13e} ({it_off} it, min s {s_off:.4f}), on {w_on:.13e} ({it_on} it, "
          f"min s {s_on:.4f}), activation 0.5: {w_half:.13e} (min s {s_half:.4f})")
    assert S_HAT < s_off < 0.25 and s_on == pytest.approx(s_off, abs=1e-6)
    assert w_on == pytest.approx(w_off, rel=1e-10)
    assert w_half > 1.01 * w_off and s_half > 0.3


def test_hessian_pattern_has_the_barrier_blocks() -> None:
    """The assembled Hessian equals the sum of the local barrier blocks (order 2 oracle)."""
    x, top, rest, ref = squashed("plate", 0.05)
    energy = ShellEnergy(top, rest, ShellParams(k_L=0.0, k_B=0.0, k_P=0.0, k_F=1.5,
                                                flip_quality=1.0))
    ev = energy.evaluate(x)
    w = barrier_weights(rest.positions, top.faces)
    local = flip_barrier(x, top.faces, rest.rest_areas, w, ref, s_hat=S_HAT, stiffness=1.5)
    dense = np.zeros((x.size, x.size))
    for f, face in enumerate(top.faces):
        idx = (3 * face[:, None] + np.arange(3)).reshape(-1)
        dense[np.ix_(idx, idx)] += local.blocks[f]
    assert isinstance(ev.hess, sp.csr_matrix)
    np.testing.assert_allclose(ev.hess.toarray(), dense, atol=1e-12 * np.abs(dense).max())
    assert ev.value == pytest.approx(local.value, rel=1e-14)
