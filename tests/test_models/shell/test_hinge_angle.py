"""Hinge angle and bending energy: values, signs, invariances and Taylor tests of the exact
gradient and Hessian (Tamstorf & Grinspun 2013) on random, near-folded and thin hinges."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError
from meshes.shells import icosphere, irregular_plate
from models.shell.assembly import StencilPattern, assemble
from models.shell.bending import (
    bending_energy_density,
    hinge_bending,
    hinge_weights,
)
from models.shell.hinge_angle import hinge_angle_derivatives, hinge_angles
from models.shell.topology import ShellTopology

ONE = np.array([[0, 1, 2, 3]], dtype=np.int64)
EPS_STEPS = 2.0 ** -np.arange(6)


def folded_hinge(alpha: float, height: float = 1.0, skew: float = 0.0) -> np.ndarray:
    """Hinge on the x-axis whose two wings drop by ``alpha`` below the xy-plane.

    Face 0 (i, j, k) and face 1 (j, i, l) have +z normals when ``alpha = 0``; ``alpha > 0`` is a
    convex fold (roof ridge under outward +z normals), whose bend angle is ``2 alpha``.
    """
    c, s = height * np.cos(alpha), height * np.sin(alpha)
    return np.array([[0.0, 0, 0], [1, 0, 0], [0.5 + skew, c, -s], [0.5 - skew, -c, -s]])


def slope(eps: np.ndarray, remainder: np.ndarray) -> float:
    """Fitted log-log slope of a Taylor remainder."""
    return float(np.polyfit(np.log(eps), np.log(remainder), 1)[0])


def theta_taylor(x: np.ndarray, hinges: np.ndarray, d: np.ndarray, eps0: float
                 ) -> tuple[float, float]:
    """Slopes of max_h |theta(x+ed)-theta-e g.d| and max |g(x+ed)-g-e H d| (both should be 2)."""
    eps = eps0 * EPS_STEPS
    dl = d[hinges].reshape(-1, 12)
    t0, g0, h0 = hinge_angle_derivatives(x, hinges)
    gd, hd = np.einsum("ha,ha->h", g0, dl), np.einsum("hab,hb->ha", h0, dl)
    r1, r2 = [], []
    for e in eps:
        t1, g1, _ = hinge_angle_derivatives(x + e * d, hinges, hessian=False)
        r1.append(np.abs(t1 - t0 - e * gd).max())
        r2.append(np.abs(g1 - g0 - e * hd).max())
    return slope(eps, np.array(r1)), slope(eps, np.array(r2))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A random proper rotation matrix."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q *= np.sign(np.diag(r))
    return q * np.sign(np.linalg.det(q))


# ---------------------------------------------------------------------------------- values


def test_flat_hinge_has_zero_angle() -> None:
    assert hinge_angles(folded_hinge(0.0, skew=0.3), ONE)[0] == 0.0


@pytest.mark.parametrize("alpha", [0.3, -0.3, 1.2, -1.2, np.pi / 2 - 5e-4, -(np.pi / 2 - 5e-4)])
def test_known_fold_angle_and_sign(alpha: float) -> None:
    theta = hinge_angles(folded_hinge(alpha, skew=0.2), ONE)[0]
    assert theta == pytest.approx(2 * alpha, rel=1e-13, abs=1e-15)


def test_angle_is_continuous_and_linear_across_zero() -> None:
    alphas = np.linspace(-1e-7, 1e-7, 21)
    thetas = np.array([hinge_angles(folded_hinge(a), ONE)[0] for a in alphas])
    assert np.all(np.diff(thetas) > 0)
    np.testing.assert_allclose(thetas, 2 * alphas, rtol=1e-9, atol=1e-22)


def test_rigid_motion_invariance_of_angle_and_covariance_of_derivatives(rng) -> None:
    x = rng.standard_normal((4, 3))
    rot, shift = random_rotation(rng), rng.standard_normal(3)
    t0, g0, h0 = hinge_angle_derivatives(x, ONE)
    t1, g1, h1 = hinge_angle_derivatives(x @ rot.T + shift, ONE)
    big = np.kron(np.eye(4), rot)
    assert t1[0] == pytest.approx(t0[0], abs=1e-13)
    np.testing.assert_allclose(g1[0], big @ g0[0], atol=1e-12 * np.abs(g0).max())
    np.testing.assert_allclose(h1[0], big @ h0[0] @ big.T, atol=1e-12 * np.abs(h0).max())


def test_angle_hessian_symmetric_with_rigid_null_space(rng) -> None:
    x = rng.standard_normal((4, 3))
    _, g, h = hinge_angle_derivatives(x, ONE)
    hh = h[0]
    assert np.abs(hh - hh.T).max() <= 1e-13 * np.abs(hh).max()
    translation = np.tile(np.eye(3), (4, 1))  # columns: unit translations (12, 3)
    assert np.abs(hh @ translation).max() <= 1e-12 * np.abs(hh).max()
    assert np.abs(g[0] @ translation).max() <= 1e-13 * np.abs(g).max()


# ------------------------------------------------------------------------ Taylor: theta


@pytest.mark.parametrize("seed", range(4))
def test_theta_taylor_random_hinges(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((4, 3))
    s1, s2 = theta_taylor(x, ONE, rng.standard_normal((4, 3)), 1e-3)
    print(f"random hinge {seed}: theta slope {s1:.3f}, grad slope {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2


@pytest.mark.parametrize("alpha", [np.pi / 2 - 5e-4, -(np.pi / 2 - 5e-4)])
def test_theta_taylor_near_pi(alpha: float, rng) -> None:
    x = folded_hinge(alpha, skew=0.2)
    theta = hinge_angles(x, ONE)[0]
    assert abs(theta) == pytest.approx(np.pi - 1e-3, rel=1e-12)
    s1, s2 = theta_taylor(x, ONE, rng.standard_normal((4, 3)), 2e-5)
    print(f"theta={theta:.6f}: slopes {s1:.3f} {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2


@pytest.mark.parametrize("alpha,skew", [(0.0, 0.3), (0.4, 0.3), (-1.0, 0.3), (0.7, 1.0)])
def test_theta_taylor_thin_triangles(alpha: float, skew: float, rng) -> None:
    # height / edge = 1e-3 on both faces; skew 1.0 puts the apex beyond the edge (t = 1.5)
    x = folded_hinge(alpha, height=1e-3, skew=skew)
    _, g, h = hinge_angle_derivatives(x, ONE)
    assert np.all(np.isfinite(h)) and np.abs(g).max() == pytest.approx(1e3, rel=0.5)
    s1, s2 = theta_taylor(x, ONE, rng.standard_normal((4, 3)), 1e-6)
    print(f"thin alpha={alpha} skew={skew}: slopes {s1:.3f} {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2


def test_thin_triangle_gradient_matches_height_formula() -> None:
    x = folded_hinge(0.0, height=1e-3, skew=0.3)
    _, g, _ = hinge_angle_derivatives(x, ONE)
    # d theta / d x_k = -n0_hat / h0 = (0, 0, -1e3); same for l.
    np.testing.assert_allclose(g[0, 6:9], [0, 0, -1e3], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(g[0, 9:12], [0, 0, -1e3], rtol=1e-12, atol=1e-9)


def test_theta_taylor_random_mesh(rng) -> None:
    p, f = irregular_plate(80, seed=3)
    p[:, 2] = 0.3 * np.sin(3 * p[:, 0]) * np.cos(2 * p[:, 1]) + 0.02 * rng.standard_normal(len(p))
    hinges = ShellTopology.from_faces(f, len(p)).hinges
    s1, s2 = theta_taylor(p, hinges, rng.standard_normal(p.shape), 1e-4)
    print(f"random mesh ({len(hinges)} hinges): slopes {s1:.3f} {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2


# ------------------------------------------------------------------------ energy W_B


def curved_plate(rng: np.random.Generator, n: int = 100) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """Irregular plate with a curved rest shape; returns (rest, current, hinges)."""
    p, f = irregular_plate(n, seed=1)
    p[:, 2] = 0.2 * np.sin(2 * p[:, 0] + 1) * np.sin(3 * p[:, 1])
    hinges = ShellTopology.from_faces(f, len(p)).hinges
    x = p + 0.05 * rng.standard_normal(p.shape)
    return p, x, hinges


def energy_taylor(x: np.ndarray, rest: np.ndarray, hinges: np.ndarray, d: np.ndarray,
                  eps0: float, branch: np.ndarray | None = None) -> tuple[float, float]:
    """Taylor slopes of W_B (value and gradient), Hessian assembled by the generic assembler."""
    theta0, w = hinge_angles(rest, hinges), hinge_weights(rest, hinges)
    pattern = StencilPattern.from_stencils([hinges], len(x))
    ev = hinge_bending(x, hinges, theta0, w, order=2, branch=branch)
    hd = assemble(pattern, [(pattern.maps[0], ev.blocks)]) @ d.ravel()
    eps = eps0 * EPS_STEPS
    r1, r2 = [], []
    for e in eps:
        moved = hinge_bending(x + e * d, hinges, theta0, w, order=1, branch=branch)
        r1.append(abs(moved.value - ev.value - e * ev.grad @ d.ravel()))
        r2.append(np.abs(moved.grad - ev.grad - e * hd).max())
    return slope(eps, np.array(r1)), slope(eps, np.array(r2))


def test_energy_taylor_curved_rest(rng) -> None:
    rest, x, hinges = curved_plate(rng)
    s1, s2 = energy_taylor(x, rest, hinges, rng.standard_normal(x.shape), 1e-4)
    print(f"W_B Taylor on {len(hinges)} hinges: slopes {s1:.3f} {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2


@pytest.mark.parametrize("alpha,height,eps0", [(np.pi / 2 - 5e-4, 1.0, 2e-5),
                                               (-(np.pi / 2 - 5e-4), 1.0, 2e-5),
                                               (0.4, 1e-3, 1e-6)])
def test_energy_taylor_near_pi_and_thin(alpha: float, height: float, eps0: float, rng) -> None:
    x = folded_hinge(alpha, height=height, skew=0.2)
    rest = folded_hinge(alpha - 0.1, height=height, skew=0.2)
    s1, s2 = energy_taylor(x, rest, ONE, rng.standard_normal(x.shape), eps0)
    print(f"W_B Taylor alpha={alpha:.4f} height={height}: slopes {s1:.3f} {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2


def test_energy_matches_definition_and_element_values(rng) -> None:
    rest, x, hinges = curved_plate(rng)
    t0, w = hinge_angles(rest, hinges), hinge_weights(rest, hinges)
    ev = hinge_bending(x, hinges, t0, w, order=2)
    expected = w * (hinge_angles(x, hinges) - t0) ** 2
    np.testing.assert_allclose(ev.element_values, expected, rtol=1e-13, atol=1e-300)
    assert ev.value == pytest.approx(expected.sum(), rel=1e-13)
    assert hinge_bending(x, hinges, t0, w, order=0).value == pytest.approx(ev.value, rel=1e-14)


def test_weights_formula() -> None:
    x = folded_hinge(0.0, height=0.5, skew=0.1)
    assert hinge_weights(x, ONE)[0] == pytest.approx(3 * 1.0 / (0.25 + 0.25), rel=1e-14)


def test_rest_state_zero_energy_and_gradient_also_after_rigid_motion(rng) -> None:
    p, f = icosphere(2)
    hinges = ShellTopology.from_faces(f, len(p)).hinges
    t0, w = hinge_angles(p, hinges), hinge_weights(p, hinges)
    ev = hinge_bending(p, hinges, t0, w, order=1)
    # zero up to round-off (the fused kernel may contract multiply-adds differently)
    assert ev.value < 1e-28 and np.abs(ev.grad).max() < 1e-12
    moved = p @ random_rotation(rng).T + rng.standard_normal(3)
    ev = hinge_bending(moved, hinges, t0, w, order=1)
    assert ev.value < 1e-26 and np.abs(ev.grad).max() < 1e-12


def test_energy_rigid_motion_invariance(rng) -> None:
    rest, x, hinges = curved_plate(rng)
    t0, w = hinge_angles(rest, hinges), hinge_weights(rest, hinges)
    e0 = hinge_bending(x, hinges, t0, w, order=0).value
    e1 = hinge_bending(x @ random_rotation(rng).T + 3.0, hinges, t0, w, order=0).value
    assert e0 > 1.0 and e1 == pytest.approx(e0, rel=1e-12)


def test_hessian_modes_symmetric_psd_and_consistent(rng) -> None:
    rest, x, hinges = curved_plate(rng)
    t0, w = hinge_angles(rest, hinges), hinge_weights(rest, hinges)
    ex, gn, pr = (hinge_bending(x, hinges, t0, w, order=2, hessian_mode=m).blocks
                  for m in ("exact", "gauss_newton", "projected"))
    for b in (ex, gn, pr):
        assert np.abs(b - b.transpose(0, 2, 1)).max() <= 1e-12 * np.abs(b).max()
    lam_ex, lam_gn, lam_pr = (np.linalg.eigvalsh(b) for b in (ex, gn, pr))
    scale = np.abs(lam_ex).max(axis=1)
    print(f"min eigenvalue / max: exact {np.min(lam_ex[:, 0] / scale):.3e}, "
          f"GN {np.min(lam_gn[:, 0] / scale):.3e}, projected {np.min(lam_pr[:, 0] / scale):.3e}")
    assert np.mean(lam_ex[:, 0] < -1e-8 * scale) > 0.2  # the exact Hessian is indefinite
    assert np.all(lam_gn[:, 0] >= -1e-12 * scale) and np.all(lam_pr[:, 0] >= -1e-12 * scale)
    _, g, h = hinge_angle_derivatives(x, hinges)
    d = hinge_angles(x, hinges) - t0
    np.testing.assert_allclose(gn, 2 * w[:, None, None] * g[:, :, None] * g[:, None, :],
                               rtol=1e-12, atol=1e-12 * np.abs(gn).max())
    np.testing.assert_allclose(ex - gn, 2 * (w * d)[:, None, None] * h, rtol=1e-9,
                               atol=1e-11 * np.abs(ex).max())
    lam, vec = np.linalg.eigh(ex)  # reference clamp in numpy
    clamped = np.einsum("hij,hj,hkj->hik", vec, np.maximum(lam, 0.0), vec)
    np.testing.assert_allclose(pr, clamped, atol=1e-12 * np.abs(ex).max())


def test_energy_density_integrates_to_energy(rng) -> None:
    rest, x, hinges = curved_plate(rng)
    faces = irregular_plate(100, seed=1)[1]
    t0, w = hinge_angles(rest, hinges), hinge_weights(rest, hinges)
    area = 0.5 * np.linalg.norm(np.cross(rest[faces[:, 1]] - rest[faces[:, 0]],
                                         rest[faces[:, 2]] - rest[faces[:, 0]]), axis=1)
    va = np.bincount(faces.ravel(), weights=np.repeat(area / 3, 3), minlength=len(rest))
    rho = bending_energy_density(x, hinges, t0, w, va)
    assert (rho * va).sum() == pytest.approx(hinge_bending(x, hinges, t0, w, order=0).value,
                                             rel=1e-12)


def test_input_errors_name_the_field(rng) -> None:
    rest, x, hinges = curved_plate(rng)
    t0, w = hinge_angles(rest, hinges), hinge_weights(rest, hinges)
    with pytest.raises(InputError, match="hessian_mode"):
        hinge_bending(x, hinges, t0, w, hessian_mode="newton")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="order"):
        hinge_bending(x, hinges, t0, w, order=3)
    with pytest.raises(InputError, match="theta0"):
        hinge_bending(x, hinges, t0[:-1], w)
    with pytest.raises(InputError, match="hinges"):
        hinge_bending(x, hinges.astype(np.int32), t0, w)
    with pytest.raises(InputError, match="non-finite"):
        hinge_bending(np.where(x == x[0, 0], np.nan, x), hinges, t0, w)
    flat = folded_hinge(0.0)
    flat[2] = flat[0]  # zero-area face 0
    with pytest.raises(InputError, match="hinge 0"):
        hinge_weights(flat, ONE)


def test_collapsed_current_face_gives_infinite_energy() -> None:
    rest = folded_hinge(0.2)
    x = rest.copy()
    x[2] = 0.5 * (x[0] + x[1])  # face 0 collapses onto the edge
    ev = hinge_bending(x, ONE, hinge_angles(rest, ONE), hinge_weights(rest, ONE), order=2)
    assert ev.value == np.inf


# ------------------------------------------------------------------ branches past +-pi


def test_a_fold_followed_past_pi_keeps_a_smooth_growing_energy(rng) -> None:
    """With a reference angle the hinge angle is taken on the branch nearest to it: a fold
    closing past flat-on-flat (bend angle 2.9 .. 3.4, the wings through each other beyond pi)
    costs ``w theta^2``, continuous and growing, where ``(-pi, pi]`` jumps to ``w (theta -
    2 pi)^2``; near the reference the evaluation is bit for bit the one without it, and the
    gradient and Hessian pass Taylor tests across pi."""
    rest = folded_hinge(0.0, skew=0.2)
    theta0, w = hinge_angles(rest, ONE), hinge_weights(rest, ONE)
    branch = np.array([3.0])
    angles = np.linspace(2.9, 3.4, 11)
    followed, raw = [], []
    for theta in angles:
        x = folded_hinge(theta / 2, skew=0.2)
        followed.append(hinge_bending(x, ONE, theta0, w, order=0, branch=branch).value)
        raw.append(hinge_bending(x, ONE, theta0, w, order=0).value)
    np.testing.assert_allclose(followed, w[0] * angles ** 2, rtol=1e-12)
    beyond = angles > np.pi
    np.testing.assert_allclose(np.array(raw)[beyond], w[0] * (angles[beyond] - 2 * np.pi) ** 2,
                               rtol=1e-12)
    assert np.all(np.diff(followed) > 0.0)
    x = folded_hinge(2.9 / 2, skew=0.2)
    with_ref = hinge_bending(x, ONE, theta0, w, order=2, branch=branch)
    without = hinge_bending(x, ONE, theta0, w, order=2)
    assert with_ref.value == without.value
    assert with_ref.grad is not None and without.grad is not None
    assert np.array_equal(with_ref.grad, without.grad)
    assert np.array_equal(with_ref.blocks, without.blocks)
    across = folded_hinge(np.pi / 2 + 5e-4, skew=0.2)  # bend angle pi + 1e-3
    s1, s2 = energy_taylor(across, rest, ONE, rng.standard_normal(across.shape), 2e-5,
                           branch=np.array([np.pi]))
    print(f"W_B Taylor across pi on the followed branch: slopes {s1:.3f} {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2
    va = np.ones(4)
    rho = bending_energy_density(across, ONE, theta0, w, va, branch=np.array([np.pi]))
    assert rho.sum() == pytest.approx(w[0] * (np.pi + 1e-3) ** 2, rel=1e-9)
    with pytest.raises(InputError, match="branch"):
        hinge_bending(across, ONE, theta0, w, branch=np.zeros(2))


def test_the_fold_contact_holds_a_closing_fold_at_its_faces_touching(rng) -> None:
    """``contact``: nothing changes (bit for bit) while ``pi - |theta| >= contact_gap``; in the
    gap each hinge pays ``c w b(pi - |theta|)`` on top of its bending (both fold signs), with
    gradient and Hessian passing Taylor tests there, and +inf once the fold has closed past
    flat-on-flat on its followed branch (a line search cannot tunnel through)."""
    rest = folded_hinge(0.0, skew=0.2)
    theta0, w = hinge_angles(rest, ONE), hinge_weights(rest, ONE)
    open_fold = folded_hinge(2.9 / 2, skew=0.2)
    a = hinge_bending(open_fold, ONE, theta0, w, order=2, contact=3.0)
    b = hinge_bending(open_fold, ONE, theta0, w, order=2)
    assert a.value == b.value and a.grad is not None and b.grad is not None
    assert np.array_equal(a.grad, b.grad) and np.array_equal(a.blocks, b.blocks)
    for sign in (1.0, -1.0):
        theta = sign * (np.pi - 0.04)
        x = folded_hinge(theta / 2, skew=0.2)
        gap, d_hat = 0.04, 0.1
        barrier = -(gap - d_hat) ** 2 * np.log(gap / d_hat)
        ev = hinge_bending(x, ONE, theta0, w, order=0, contact=3.0, contact_gap=d_hat)
        assert ev.value == pytest.approx(w[0] * theta ** 2 + 3.0 * w[0] * barrier, rel=1e-9)
    near = folded_hinge((np.pi - 0.04) / 2, skew=0.2)
    pattern = StencilPattern.from_stencils([ONE], 4)
    ev = hinge_bending(near, ONE, theta0, w, order=2, contact=3.0)
    d = rng.standard_normal(near.shape)
    hd = assemble(pattern, [(pattern.maps[0], ev.blocks)]) @ d.ravel()
    eps = 1e-5 * EPS_STEPS
    r1, r2 = [], []
    for e in eps:
        moved = hinge_bending(near + e * d, ONE, theta0, w, order=1, contact=3.0)
        r1.append(abs(moved.value - ev.value - e * ev.grad @ d.ravel()))
        r2.append(np.abs(moved.grad - ev.grad - e * hd).max())
    s1, s2 = slope(eps, np.array(r1)), slope(eps, np.array(r2))
    print(f"fold contact Taylor at a gap of 0.04 rad: slopes {s1:.3f} {s2:.3f}")
    assert 1.8 <= s1 <= 2.2 and 1.8 <= s2 <= 2.2
    through = folded_hinge((np.pi + 0.05) / 2, skew=0.2)  # closed 0.05 rad past pi
    closed = hinge_bending(through, ONE, theta0, w, order=0, contact=3.0,
                           branch=np.array([np.pi]))
    assert closed.value == np.inf
    with pytest.raises(InputError, match="fold_contact"):
        hinge_bending(near, ONE, theta0, w, contact=-1.0)
