"""The rigid-ball integrator of models/rigid.py: free fall, penalty bounces, the interface
solver, the contact stiffness dR/dc (Taylor test), the penetration geometry, validation."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError, SolverError
from models.contact import point_triangle_distance
from models.rigid import (
    BallState,
    RigidBallOptions,
    RigidCouplingOptions,
    advance,
    predict,
    scheme,
)
from solvers.coupling import BallCoupling, broyden_solve

G = np.array([0.0, 0.0, -9.81])


def free_state(c0: np.ndarray, w0: np.ndarray) -> BallState:
    return BallState(c0[None].copy(), w0[None].copy(), G[None].copy(), np.zeros((1, 3)))


@pytest.mark.parametrize("dynamics", ["implicit_euler", "newmark"])
def test_free_fall_is_the_schemes_exact_discrete_solution(dynamics):
    """Implicit Euler: c_n = c_0 + w_0 t + g h^2 n (n+1)/2 (the body's own free fall, see
    test_cli_run); Newmark (average acceleration): the exact parabola c_0 + w_0 t + g t^2/2."""
    h, c0, w0 = 0.01, np.array([0.1, -0.2, 1.0]), np.array([0.5, 0.0, 2.0])
    st = free_state(c0, w0)
    for n in range(1, 51):
        st = advance(st, predict(st, h, dynamics), G[None], np.zeros((1, 3)), h, dynamics)
        t = n * h
        drop = G * h * h * n * (n + 1) / 2 if dynamics == "implicit_euler" else G * t * t / 2
        np.testing.assert_allclose(st.center[0], c0 + w0 * t + drop, rtol=0, atol=1e-13)
        np.testing.assert_allclose(st.velocity[0], w0 + G * t, rtol=0, atol=1e-13)


def bounce(dynamics: str, h: float, k: float = 1e5, g: float = -9.81, z0: float = 0.2,
           v0: float = -2.0, T: float = 0.4, m: float = 1.0, r: float = 0.1
           ) -> tuple[np.ndarray, np.ndarray, BallState]:
    """A ball on a rigid floor z = 0 held by the penalty k/2 <z - r>_-^2, stepped like
    BallCoupling.step does (interface residual solved by broyden_solve). Returns the energy
    (kinetic + gravity + penalty) and height per step and the final state."""
    grav = np.array([0.0, 0.0, g])
    beta = scheme(dynamics)[0]
    st = BallState(np.array([[0.0, 0.0, z0]]), np.array([[0.0, 0.0, v0]]), grav[None].copy(),
                   np.zeros((1, 3)))

    def force(c: np.ndarray) -> np.ndarray:
        return np.array([0.0, 0.0, k * max(r - c[2], 0.0)])

    def energy(s: BallState) -> float:
        z = s.center[0, 2]
        kinetic = 0.5 * m * float(s.velocity[0] @ s.velocity[0])
        return kinetic - m * g * z + 0.5 * k * max(r - z, 0) ** 2

    E, z = [energy(st)], [z0]
    for _ in range(int(round(T / h))):
        cp = predict(st, h, dynamics)[0]
        c, _, mismatch = broyden_solve(
            lambda c, cp=cp: c - cp - beta * h * h * (grav + force(c) / m),
            cp + beta * h * h * st.acceleration[0],
            lambda c, res: np.eye(3) + beta * h * h / m * np.diag([0, 0, k * (c[2] < r)]),
            1e-13, 50)
        assert mismatch <= 1e-13
        F = force(c)
        st = advance(st, cp[None], grav + F / m, F[None], h, dynamics)
        E.append(energy(st))
        z.append(st.center[0, 2])
    return np.array(E), np.array(z), st


def test_newmark_bounce_conserves_energy_off_the_contact_kink():
    """Average acceleration conserves the energy of a quadratic potential exactly: every step
    that stays in flight or stays in contact keeps E to round-off; only the steps crossing
    the kink of the penalty err, by O(h^2) (fitted)."""
    totals = []
    hs = np.array([5e-4, 2.5e-4, 1.25e-4])
    for h in hs:
        E, z, _ = bounce("newmark", h)
        touching = z < 0.1
        same = touching[1:] == touching[:-1]
        steps = np.abs(np.diff(E)) / E[0]
        assert steps[same].max() < 1e-13  # measured 1.9e-15 .. 3.4e-15
        assert (~same).sum() >= 2  # the bounce happened (in and out of contact)
        totals.append(abs(E[-1] - E[0]) / E[0])
    rate = np.polyfit(np.log(hs), np.log(totals), 1)[0]
    assert 1.7 < rate < 2.3, (totals, rate)  # measured 2.03 (1.1e-3, 2.6e-4, 6.5e-5)


def test_implicit_euler_bounce_dissipates_as_predicted():
    """Implicit Euler on a convex potential never gains energy; the restitution of a bounce
    (gravity off) is the scheme's amplitude decay 1/sqrt(1 + (omega h)^2) over the contact time
    pi/omega: log e = -(pi/2) omega h + O((omega h)^2), slope fitted."""
    E, _, st = bounce("implicit_euler", 1e-3)
    assert np.all(np.diff(E) <= 1e-12 * E[0])
    assert E[-1] < 0.5 * E[0]
    omega_h, log_e = [], []
    for h in (1e-4, 5e-5, 2.5e-5):
        _, _, st = bounce("implicit_euler", h, g=0.0, T=0.1, z0=0.12)
        omega_h.append(np.sqrt(1e5) * h)
        log_e.append(np.log(st.velocity[0, 2] / 2.0))
    slope = np.polyfit(omega_h, log_e, 1)[0]
    assert abs(slope + np.pi / 2) < 0.01, slope  # measured -1.568


def test_explicit_staggering_fails_where_the_iteration_holds():
    """Why the coupling iterates: moving the ball with the last step's contact force (plain
    explicit staggering, symplectic Euler) is unstable once omega h > 2: at omega h = 3.2 a
    ball hitting the floor at 2 m/s is shot back at 6.7 m/s (11x the energy), while the
    interface iteration of the same step rebounds slower than it came, with the penetration
    below the elastic bound v sqrt(m/k)."""
    k, m, r, h = 1e7, 1.0, 0.1, 1e-3
    c, w = np.array([0.0, 0.0, 0.11]), np.array([0.0, 0.0, -2.0])
    rebound = []
    for _ in range(100):
        F = np.array([0.0, 0.0, k * max(r - c[2], 0.0)])
        w = w + h * (G + F / m)
        c = c + h * w
        rebound.append(w[2])
    assert max(rebound) > 3.0 * 2.0  # measured 6.75 m/s
    _, z, st = bounce("implicit_euler", h, k=k, z0=0.11, T=0.1)
    assert 0.0 < st.velocity[0, 2] < 2.0  # rebounding, slower than the impact
    assert r - z.min() < np.sqrt(m / k) * 2.0  # measured 0.38 mm < 0.63 mm


def test_broyden_solves_a_nonlinear_system_from_a_stiff_jacobian():
    """The interface solver converges from an over-stiff J0 (as K_rigid over-estimates the
    compliant body) on r(x) = x + 0.5 x^3 - b."""
    b = np.array([1.0, -2.0, 0.5])
    x, k, res = broyden_solve(lambda x: x + 0.5 * x**3 - b, np.zeros(3), 10.0 * np.eye(3),
                              1e-12, 100)
    assert res <= 1e-12 and k < 40  # measured 23 evaluations
    np.testing.assert_allclose(x + 0.5 * x**3, b, atol=1e-11)


def test_point_triangle_distance_against_dense_sampling():
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(200, 3, 3))
    p = rng.normal(size=3)
    exact = point_triangle_distance(p, tri)
    s = np.linspace(0.0, 1.0, 201)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1.0
    bary = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], axis=1)
    pts = np.einsum("sk,tkd->tsd", bary, tri)
    sampled = np.linalg.norm(pts - p, axis=2).min(axis=1)
    assert np.all(exact <= sampled + 1e-12)
    edge = np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1) + np.linalg.norm(tri[:, 2] - tri[:, 0],
                                                                             axis=1)
    assert np.all(sampled - exact <= edge / 200)


def test_ball_options_validation_and_mass():
    ball = RigidBallOptions(radius=0.1, mass=4.0, center=(1.0, 2.0, 3.0))
    contact = ball.contact()
    assert contact.obstacle == "sphere" and contact.radius == 0.1
    assert contact.point == (1.0, 2.0, 3.0) and contact.quadrature_degree == 6
    with pytest.raises(InputError, match="ball.mass: missing"):
        RigidBallOptions(radius=0.1)
    with pytest.raises(InputError, match="ball.mass must be > 0"):
        RigidBallOptions(radius=0.1, mass=-1.0)
    with pytest.raises(InputError, match="ball.radius"):
        RigidBallOptions(radius=0.0, mass=1.0)
    with pytest.raises(InputError, match="ball.guide"):
        RigidBallOptions(mass=1.0, guide=(0, 3))
    with pytest.raises(InputError, match="guided components"):
        RigidBallOptions(mass=1.0, guide=(0,), velocity=(1.0, 0.0, 0.0))
    with pytest.raises(InputError, match="options.rtol"):
        RigidCouplingOptions(rtol=0.0)
    with pytest.raises(InputError, match="body.dynamics"):
        scheme("static")


def test_scene_refuses_rigid_balls_in_statics(tmp_path):
    from wrinkles.scene import load_scene

    scene = tmp_path / "s.toml"
    scene.write_text('[mesh]\nbuilder = "box"\n[body]\ndynamics = "static"\n'
                     '[[rigid.balls]]\nmass = 1.0\n')
    with pytest.raises(InputError, match="s.toml: rigid.balls: rigid balls need body.dynamics"):
        load_scene(scene)
    scene.write_text('[mesh]\nbuilder = "box"\n[body]\ndynamics = "newmark"\n'
                     '[[rigid.balls]]\nmass = 1.0\nmas = 2.0\n')
    with pytest.raises(InputError, match=r"unknown key 'rigid.balls\[0\].mas' \(did you mean"):
        load_scene(scene)


def test_center_stiffness_is_the_derivative_of_the_reaction():
    """K = dR/dc assembled from center_stiffness_forms against finite differences of the
    assembled reaction (Taylor test: the remainder |R(c + e d) - R(c) - e K d| decays as e^2)."""
    from meshes.builders import box
    from models.backend import MPI, mesh_from_arrays
    from models.body import BodyOptions
    from models.materials import Material
    from models.rigid import RigidOptions
    from solvers.body import Body

    m = box(lx=0.4, ly=0.4, lz=0.2, h=0.1)
    mesh = mesh_from_arrays(MPI.COMM_WORLD, m.points, m.tets)
    ball = RigidBallOptions(radius=0.15, mass=1.0, center=(0.21, 0.19, 0.2 + 0.15 - 0.02))
    body = Body(mesh, Material(E=1e4, nu=0.3, density=100.0),
                BodyOptions(dynamics="implicit_euler", contacts=(ball.contact(),)))
    coupling = BallCoupling(body, RigidOptions(balls=(ball,)), 0)
    c = np.array(ball.center)
    K = coupling.stiffness()
    R0 = body.reaction_force(0)
    assert R0[2] < -1.0  # the ball pushes the block down
    d = np.array([0.3, -0.2, 1.0])
    eps = np.array([1e-3, 5e-4, 2.5e-4, 1.25e-4])
    rem = []
    for e in eps:
        body.set_sphere_center(c + e * d)
        rem.append(np.linalg.norm(body.reaction_force(0) - R0 - e * K @ d))
    rate = np.polyfit(np.log(eps), np.log(rem), 1)[0]
    assert rate > 1.8, (rem, rate)
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-9 * np.abs(K).max())


def _ball_on_block(dynamics: str = "implicit_euler",
                   center: tuple[float, float, float] = (0.21, 0.19, 0.2 + 0.15 + 0.002),
                   guide: tuple[int, ...] = (), **newton: int) -> BallCoupling:
    """A 2 kg ball (r = 0.15 m; 2 mm above by default) over a soft block pinned at its base,
    moving down at 1 m/s; ``newton``: body Newton options (e.g. ``max_it``, ``max_halvings``)."""
    from meshes.builders import box
    from models.backend import MPI, mesh_from_arrays
    from models.body import BodyOptions, PinSpec
    from models.materials import Material
    from models.rigid import RigidOptions
    from solvers.body import Body
    from solvers.body_newton import NewtonOptions

    m = box(lx=0.4, ly=0.4, lz=0.2, h=0.1)
    mesh = mesh_from_arrays(MPI.COMM_WORLD, m.points, m.tets)
    ball = RigidBallOptions(radius=0.15, mass=2.0, center=center, velocity=(0.0, 0.0, -1.0),
                            guide=guide)
    floor = PinSpec(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), tol=1e-6)
    body = Body(mesh, Material(E=1e4, nu=0.3, density=100.0),
                BodyOptions(dynamics=dynamics, dt=5e-3, contacts=(ball.contact(),),
                            pins=(floor,)),
                NewtonOptions(**newton))
    return BallCoupling(body, RigidOptions(balls=(ball,)), 0)


@pytest.mark.parametrize("dynamics", ["implicit_euler", "newmark"])
def test_guided_ball_moves_only_vertically_and_books_the_guide(dynamics):
    """An off-centre hit on a pinned block pushes the ball sideways; guided in x and y it
    stays on its vertical, the guide's impulse is booked, and the momentum balance (contact
    on ball = on body + supports, with the pins' reaction) holds to solver tolerance, with
    either scheme (Newmark books h/2 (F_n + F_{n+1}))."""
    coupling = _ball_on_block(dynamics, center=(0.33, 0.2, 0.2 + 0.15 + 0.002), guide=(0, 1))
    for _ in range(6):
        info = coupling.step()
    assert info.iterations >= 2 and coupling.state.force[0, 2] > 1.0  # in contact
    np.testing.assert_array_equal(coupling.state.center[0, :2], [0.33, 0.2])
    np.testing.assert_array_equal(coupling.state.velocity[0, :2], 0.0)
    assert abs(coupling.state.force[0, 0]) > 0.05 * coupling.state.force[0, 2]  # sideways push
    bal = {k: np.array(v) for k, v in coupling.balance().items()}
    assert abs(bal["guide_impulse"][0]) > 1e-3
    scale = np.abs(bal["ball_impulse"]).max()
    np.testing.assert_allclose(bal["ball_impulse"] + bal["body_impulse"], 0.0, rtol=0,
                               atol=1e-6 * scale)
    np.testing.assert_allclose(bal["body_impulse"], bal["contact_impulse"], rtol=0,
                               atol=1e-6 * scale)
    assert np.abs(bal["ground_impulse"]).max() > 0.1 * scale  # the pins held the block


def test_interface_stiffness_is_the_derivative_of_the_reaction_of_the_body_in_equilibrium():
    """dR/dc of a sphere against a soft block that answers it: the block's step re-solved
    with the centre moved (R(c + e d) from a new equilibrium u(c + e d)) against
    K_c - G^T A^{-1} G (Taylor: the remainder decays as e^2; with the rigid-surface K_c
    alone as e, since the compliant block gives way)."""
    from meshes.builders import box
    from models.backend import MPI, mesh_from_arrays
    from models.body import BodyOptions, PinSpec
    from models.materials import Material
    from models.rigid import RigidOptions
    from solvers.body import Body
    from solvers.body_newton import NewtonOptions

    m = box(lx=0.4, ly=0.4, lz=0.2, h=0.1)
    mesh = mesh_from_arrays(MPI.COMM_WORLD, m.points, m.tets)
    ball = RigidBallOptions(radius=0.15, mass=1.0, center=(0.21, 0.19, 0.2 + 0.15 - 0.01))
    pins = (PinSpec(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0)),)
    body = Body(mesh, Material(E=1e4, nu=0.3, density=100.0),
                BodyOptions(dynamics="implicit_euler", dt=0.01, contacts=(ball.contact(),),
                            pins=pins),
                NewtonOptions(rtol=1e-12, atol=1e-12))
    coupling = BallCoupling(body, RigidOptions(balls=(ball,)), 0)
    saved = body.snapshot()

    def reaction(c: np.ndarray) -> np.ndarray:
        body.restore(saved)
        body.set_sphere_center(c)
        body.step()
        return body.reaction_force(0)

    c = np.array(ball.center)
    R0 = reaction(c)
    K_rigid, K = coupling.stiffness(), coupling.interface_stiffness()
    assert R0[2] < -1.0
    assert 0.0 < K[2, 2] < 0.9 * K_rigid[2, 2]  # the block gives way
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-9 * np.abs(K).max())
    d = np.array([0.3, -0.2, 1.0])
    eps = np.array([2e-3, 1e-3, 5e-4, 2.5e-4])
    rem, rem_rigid = [], []
    for e in eps:
        dR = reaction(c + e * d) - R0
        rem.append(np.linalg.norm(dR - e * K @ d))
        rem_rigid.append(np.linalg.norm(dR - e * K_rigid @ d))
    rate = np.polyfit(np.log(eps), np.log(rem), 1)[0]
    rate_rigid = np.polyfit(np.log(eps), np.log(rem_rigid), 1)[0]
    assert rate > 1.8, (rem, rate)
    assert rate_rigid < 1.2, (rem_rigid, rate_rigid)


def test_the_interface_iteration_starts_with_a_newton_step_against_the_compliant_body():
    """Eight steps of a ball denting a soft block: with the first secant K_c - G^T A^{-1} G
    and the extrapolated guess every step (all in contact) takes at most 3 body solves, fewer in
    all than from the rigid-surface K_c (whose first update overshoots the soft block), to
    the same state within the interface tolerance."""
    runs = {}
    for label in ("compliant", "rigid"):
        coupling = _ball_on_block()
        if label == "rigid":
            coupling.interface_stiffness = coupling.stiffness  # type: ignore[method-assign]
        solves = [coupling.step().iterations for _ in range(8)]
        runs[label] = (solves, coupling.state.center.copy())
    solves, center = runs["compliant"]
    assert max(solves) <= 3 and min(solves) >= 2, solves  # in contact from the first step
    assert sum(solves) < sum(runs["rigid"][0]), runs
    tol = 1e-8 * 0.15
    np.testing.assert_allclose(center, runs["rigid"][1], rtol=0, atol=10 * tol)


def test_a_restored_ball_state_steps_as_the_uninterrupted_one():
    """The checkpoint arrays of the balls (with the previous acceleration that the guess
    extrapolates) restore a coupling that steps bitwise like the one that wrote them; an
    older checkpoint without that array restarts with the guess a_n."""
    straight = _ball_on_block()
    for _ in range(4):
        straight.step()
    arrays = {k: np.array(v, copy=True) for k, v in straight.arrays().items()}
    body_state = straight.body.snapshot()
    straight.step()
    resumed = _ball_on_block()
    resumed.body.restore(body_state)
    resumed.restore(arrays)
    resumed.step()
    np.testing.assert_array_equal(resumed.state.center, straight.state.center)
    np.testing.assert_array_equal(resumed.body.u.x.array, straight.body.u.x.array)
    old = {k: v for k, v in arrays.items() if k != "previous_acceleration"}
    resumed.restore(old)
    np.testing.assert_array_equal(resumed.previous_acceleration, arrays["acceleration"])


def test_the_ball_stiffness_over_its_contact_facets_is_the_one_over_all_facets(monkeypatch):
    """K_c and the compliance G^T A^{-1} G integrated over the facets that carry the ball's
    penalty (``Body.contact_domains``) are the sums over all exterior facets; a selection
    that leaves a penetrated facet out is refused (None: all facets)."""
    import solvers.contact_set as contact_set

    coupling = _ball_on_block()
    for _ in range(3):
        coupling.step()  # pressed in
    body = coupling.body
    domains = body.contact_domains()
    assert domains is not None
    ball = body.contacts[coupling.indices[0]].facet_id
    kept, every = domains[ball].size // 2, body._active.pairs.shape[0]
    K, K_all = coupling.stiffness(domains), coupling.stiffness()
    S, S_all = (body.obstacle_compliance(coupling.indices, d) for d in (domains, None))
    print(f"{kept} of {every} facets; |K - K_all| = {np.abs(K - K_all).max():.2e} of "
          f"{np.abs(K_all).max():.3e} N/m, |S - S_all| = {np.abs(S - S_all).max():.2e} of "
          f"{np.abs(S_all).max():.3e} N/m")
    assert np.abs(K_all).max() > 0 and 0 < kept < every / 4
    np.testing.assert_allclose(K, K_all, rtol=0, atol=1e-13 * np.abs(K_all).max())
    np.testing.assert_allclose(S, S_all, rtol=0, atol=1e-12 * np.abs(S_all).max())
    monkeypatch.setattr(contact_set, "SLACK", -2.0)  # a margin below the ball's dent
    assert body.contact_domains() is None


def test_an_indefinite_compliance_falls_back_to_the_rigid_stiffness():
    """A compliance G^T A^{-1} G that is not positive semidefinite (a body whose Jacobian is
    not positive definite) gives the rigid K_c, the secant used before; a semidefinite one
    is subtracted."""
    coupling = _ball_on_block()
    coupling.step()  # in contact
    K = coupling.stiffness()
    assert np.any(K)
    spd = np.diag([1.0, 2.0, 3.0])
    for S, expected in ((spd, K - spd), (-spd, K), (np.diag([1.0, -1e-3, 3.0]), K)):
        coupling.body.obstacle_compliance = lambda indices, domains=None, S=S: S  # type: ignore[method-assign]
        np.testing.assert_array_equal(coupling.interface_stiffness(), expected)


def test_a_halved_ball_step_halves_the_balls_too_and_keeps_the_ledger():
    """Body Newton capped at 2 iterations: the coupled steps halve (balls with the body), and
    ball + body impulse cancel to round-off as in unhalved steps (a body halving alone left
    1.25 N s of 0.23 N s exchanged); six steps still end at t = 6 dt, near the unhalved
    run's ball."""
    halved, plain = _ball_on_block(max_it=2), _ball_on_block()
    halvings = [halved.step().report.halvings for _ in range(6)]
    for _ in range(6):
        plain.step()
    assert sum(halvings) >= 6, halvings
    assert halved.body.t == pytest.approx(6 * 5e-3, rel=1e-12)
    bal = {k: np.array(v) for k, v in halved.balance().items()}
    scale = np.abs(bal["ball_impulse"]).max()
    np.testing.assert_allclose(bal["ball_impulse"] + bal["body_impulse"], 0.0, rtol=0,
                               atol=1e-9 * scale)
    np.testing.assert_allclose(bal["body_impulse"], bal["contact_impulse"], rtol=0,
                               atol=1e-9 * scale)
    # implicit Euler at smaller steps: the same motion to first order in h
    assert np.abs(halved.state.center - plain.state.center).max() < 2e-3


def test_a_ball_step_that_fails_every_halving_restores_balls_ledger_and_body():
    """No halving allowed and a body Newton of one iteration: the step raises, and balls,
    ledger, time and body displacement are those before it."""
    coupling = _ball_on_block(max_it=1, max_halvings=1)
    before = (coupling.state.copy(), coupling.body.t, coupling.body.u.x.array.copy(),
              {k: np.array(v, copy=True) for k, v in coupling.arrays().items()})
    with pytest.raises(SolverError):
        coupling.step()
    state, t, u, arrays = before
    np.testing.assert_array_equal(coupling.state.center, state.center)
    np.testing.assert_array_equal(coupling.state.velocity, state.velocity)
    assert coupling.body.t == t
    np.testing.assert_array_equal(coupling.body.u.x.array, u)
    for k, v in coupling.arrays().items():
        np.testing.assert_array_equal(v, arrays[k], err_msg=k)
