"""Coupled iterations: the embedded shell with the body, and rigid balls with the body.

* Shell <-> body (Remillard & Kry 2013, two-way) as a fixed point; the default two-way scheme
  is one Newton solve of both instead (:mod:`solvers.monolithic`). Per frame the body is
  re-stepped with the cluster penalty, shell held fixed, as a quadratic term of its energy
  (:class:`models.coupling.PenaltyCoupling`), then the shell is re-solved for the new target;
  the body load ``c = M (x - X_T)`` is extrapolated by :class:`Anderson` acceleration
  (:func:`coupled_frame`). Without acceleration this is block Gauss-Seidel on the total
  energy ``Pi(u) + W(x, y(u))``, monotone but slow for a stiff skin (contraction 0.90-0.98
  per iteration: docs/notes/two-way-coupling.md); kept as the reference the monolithic
  solve is tested against.
* Rigid balls <-> body (:class:`BallCoupling`): per body step the interface equation of the
  ball positions is solved by Broyden's method (:func:`broyden_solve`), each residual a body
  step with the spheres moved, its Newton started from the previous residual's solution, the
  first secant the Newton Jacobian of the balls against the compliant body
  (:meth:`BallCoupling.interface_stiffness`; :mod:`models.rigid` has the scheme, the guess
  and the momentum ledger).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from meshes.errors import InputError, SolverError
from models.backend import MPI, dolfinx, global_scalar, with_facet_domains
from models.coupling import PenaltyCoupling
from models.rigid import (
    BallState,
    BoundaryFacets,
    Ledger,
    RigidOptions,
    RigidStepInfo,
    advance,
    impulse,
    initial_state,
    predict,
    scheme,
)

CouplingMode = Literal["one_way", "two_way"]
CouplingScheme = Literal["monolithic", "implicit"]


@dataclass(frozen=True)
class CouplingOptions:
    """How the shell acts back on the body.

    Attributes:
        mode: ``"one_way"`` (the shell follows the body, Algorithm 1 of the draft) or
            ``"two_way"`` (the penalty acts on the body too).
        scheme: ``"monolithic"`` (one Newton solve of body and shell per body step,
            :mod:`solvers.monolithic`) or ``"implicit"``, the fixed point per frame
            (:func:`coupled_frame`: the penalty, shell fixed, is a quadratic term of the body's
            energy; Anderson on the body load); docs/notes/two-way-coupling.md.
        max_iterations: body/shell iterations per frame (fixed point), >= 1; a frame that
            reaches it is kept but flagged ``coupling_converged = false``.
        rtol: fixed point converged when ``max|u_k - u_{k-1}| <= rtol max|u_k|``
            (dimensionless).
        memory: difference columns of the Anderson least-squares secant, >= 1.

    """

    mode: CouplingMode = "one_way"
    max_iterations: int = 100
    rtol: float = 1e-6
    memory: int = 8
    scheme: CouplingScheme = "monolithic"

    def __post_init__(self) -> None:
        if self.mode not in ("one_way", "two_way"):
            raise InputError(f"shell.coupling.mode: expected 'one_way' or 'two_way', "
                             f"got {self.mode!r}")
        if self.scheme not in ("monolithic", "implicit"):
            raise InputError(f"shell.coupling.scheme: expected 'monolithic' or 'implicit', "
                             f"got {self.scheme!r}")
        if self.memory < 1:
            raise InputError(f"shell.coupling.memory: must be >= 1, got {self.memory}")
        if self.max_iterations < 1:
            raise InputError(f"shell.coupling.max_iterations: must be >= 1, "
                             f"got {self.max_iterations}")
        if not (np.isfinite(self.rtol) and self.rtol > 0.0):
            raise InputError(f"shell.coupling.rtol: must be > 0, got {self.rtol}")


@dataclass
class Anderson:
    """Anderson acceleration of a fixed-point iteration ``x -> G(x)`` (IQN-ILS).

    Anderson 1965; Degroote, Bathe & Vierendeels 2009 (interface quasi-Newton with an
    inverse Jacobian from a least-squares model) for partitioned coupling. With the
    residuals ``r_i = G(x_i) - x_i`` and the differences ``dR_i = r_{i+1} - r_i``,
    ``dG_i = G(x_{i+1}) - G(x_i)`` of the last ``memory`` iterations,

        gamma = argmin |r_k - dR gamma|,     x_{k+1} = G(x_k) - dG gamma,

    (the first step is the plain ``x_1 = G(x_0)``): the secants of all ``memory`` slow modes
    at once, where :class:`Aitken` fits one scalar factor to all of them.

    Attributes:
        memory: number of difference columns kept, >= 1.
        rcond: relative singular value below which the least-squares problem drops a
            direction (``numpy.linalg.lstsq``).
        residuals: previous residuals ``r_i`` (oldest first, at most ``memory + 1``).
        images: previous images ``G(x_i)``, aligned with ``residuals``.
        gamma: coefficients of the last step (diagnostics).

    """

    memory: int = 8
    rcond: float = 1e-10
    residuals: list[np.ndarray] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)
    gamma: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def relax(self, x: np.ndarray, gx: np.ndarray) -> np.ndarray:
        """Return the next iterate from ``x_k`` and ``G(x_k)``."""
        r = (gx - x).reshape(-1)
        g = np.asarray(gx).reshape(-1)
        self.residuals.append(r)
        self.images.append(g)
        del self.residuals[:-(self.memory + 1)], self.images[:-(self.memory + 1)]
        if len(self.residuals) < 2:
            self.gamma = np.zeros(0)
            return np.array(gx, dtype=np.float64, copy=True)
        dR = np.diff(np.stack(self.residuals, axis=1), axis=1)
        dG = np.diff(np.stack(self.images, axis=1), axis=1)
        self.gamma = np.linalg.lstsq(dR, r, rcond=self.rcond)[0]
        return (g - dG @ self.gamma).reshape(np.shape(gx))


def relative_change(comm: MPI.Comm, new: np.ndarray, old: np.ndarray) -> float:
    """Coupling change ``max|new - old| / max|new|`` over all ranks."""
    top = comm.allreduce(float(np.abs(new - old).max(initial=0.0)), op=MPI.MAX)
    scale = comm.allreduce(float(np.abs(new).max(initial=0.0)), op=MPI.MAX)
    return float(top) / max(float(scale), 1e-300)


@dataclass(frozen=True)
class CoupledFrame:
    """Outcome of :func:`coupled_frame`.

    Attributes:
        record: the body stage's record of the last iteration.
        report: the shell solve's report of the last iteration.
        iterations: body/shell iterations done.
        change: the last relative change of the body displacement.

    """

    record: dict[str, Any]
    report: Any
    iterations: int
    change: float


def coupled_frame(body: Any, coupling: PenaltyCoupling, options: CouplingOptions,
                  offset: Callable[[], np.ndarray],
                  step_body: Callable[[], Mapping[str, Any]],
                  solve_shell: Callable[[bool], Any]) -> CoupledFrame:
    """Iterate body step and shell solve of one frame to the coupled state (collective).

    Iteration ``k`` redoes the frame's body steps from the saved state with the penalty as
    the quadratic term ``1/2 u^T K u - c_k^T u + e0`` (``K`` built once,
    :class:`models.coupling.PenaltyCoupling`), then solves the shell for the new target.
    ``c_k`` is the Anderson-extrapolated load ``M (x - X_T)`` of the shells so far. Ends when
    ``max|u_k - u_{k-1}| <= rtol max|u_k|`` or after ``max_iterations``.

    Args:
        body: the body (``solvers.body.Body``).
        coupling: the penalty's constant operators on the body's space.
        options: tolerance, cap and Anderson memory.
        offset: returns the current shell displacement ``x - X_T`` (n, 3).
        step_body: advances the body over the frame, returns its record.
        solve_shell: solves the shell for the body's current target; its argument says
            whether the frame's imperfection is added (first iteration only).

    """
    saved, comm = body.snapshot(), body.mesh.comm
    accel = Anderson(memory=options.memory)
    load = coupling.load(offset())
    record: dict[str, Any] = {}
    report, change, k = None, math.inf, 0
    for k in range(1, options.max_iterations + 1):  # noqa: B007  (k is reported)
        u_old = body.u.x.array.copy()
        body.set_quadratic_energy(coupling.load_term(load, coupling.energy(offset())))
        body.restore(saved)
        record = dict(step_body())
        change = relative_change(comm, body.u.x.array, u_old)
        report = solve_shell(k == 1)
        if change <= options.rtol:
            break
        load = accel.relax(load, coupling.load(offset()))
    return CoupledFrame(record, report, k, change)


def broyden_solve(residual: Any, x0: np.ndarray, J0: Any, tol: float,
                  max_iterations: int) -> tuple[np.ndarray, int, float]:
    """Solve ``residual(x) = 0`` (x flat) by Broyden's good method from Jacobian ``J0``.

    ``J_{k+1} = J_k + (dr - J_k dx) dx^T / (dx . dx)`` (Broyden 1965). ``J0`` is a matrix or a
    callable ``J0(x0, r0)`` evaluated after the first residual (e.g. a stiffness assembled at
    the first body solve).

    Returns:
        ``(x, iterations, max |r|)`` of the last residual evaluated; ``x`` is the point where
        the last residual was evaluated (converged or not: the caller checks ``max |r|``).

    """
    x = np.array(x0, dtype=float)
    r = residual(x)
    J = J0(x, r) if callable(J0) else np.array(J0, dtype=float)
    k = 1
    while np.max(np.abs(r)) > tol and k < max_iterations:
        dx = -np.linalg.solve(J, r)
        x_new = x + dx
        r_new = residual(x_new)
        J = J + np.outer(r_new - r - J @ dx, dx) / float(dx @ dx)
        x, r, k = x_new, r_new, k + 1
    return x, k, float(np.max(np.abs(r)))


class BallCoupling:
    """Rigid balls stepped together with a body whose contacts ``first..first+N-1`` are theirs.

    Args:
        body: The body (``solvers.body.Body``); its ``options.contacts[first + i]`` is the
            sphere of ball ``i`` (:meth:`RigidBallOptions.contact`), the other contacts and
            the pins count as ground in the :class:`Ledger`.
        options: The balls and the coupling iteration.
        first: Index of the first ball's contact in the body's contacts.

    """

    def __init__(self, body: Any, options: RigidOptions, first: int) -> None:
        if not options.balls:
            raise InputError("rigid: no balls")
        self.body, self.options = body, options
        self.dynamics = body.options.dynamics
        scheme(self.dynamics)
        self.indices = list(range(first, first + len(options.balls)))
        self.others = [i for i in range(len(body.contacts)) if i not in self.indices]
        self.mass = np.array([b.mass for b in options.balls], dtype=float)
        self.radius = np.array([b.radius for b in options.balls])
        self.free = np.array([b.free for b in options.balls])
        self.gravity = np.asarray(body.options.gravity, dtype=float)
        self.state = initial_state(options.balls, self.gravity)
        self._stiffness = [[[dolfinx.fem.form(f) for f in row]
                            for row in body.contacts[i].center_stiffness_forms(body.u)]
                           for i in self.indices]
        rho, dx = body.material.density, body.dx
        self._momentum = [dolfinx.fem.form(rho * body.v[k] * dx) for k in range(3)]
        self.body_mass = global_scalar(dolfinx.fem.form(rho * dx))
        self._surface = BoundaryFacets(body)
        self.ledger = Ledger()
        self.start()

    # --- state --------------------------------------------------------------------------------

    def start(self) -> None:
        """Begin the ledger and the forces at the body's current state (a new run)."""
        self.set_centers(self.state.center)
        self.body.initial_acceleration()  # Newmark: a_0 enters the pins' initial reaction
        self.state.force = -self.reactions()
        self.state.acceleration = self.acceleration(self.state.force)
        self.previous_acceleration = self.state.acceleration.copy()
        self.ledger = Ledger(ground_force=self.ground_force(),
                             body_momentum0=self.body_momentum(),
                             ball_momentum0=self.ball_momentum(), time0=self.body.t)

    def set_centers(self, centers: np.ndarray) -> None:
        """Move every ball's sphere obstacle (takes effect at the next body solve)."""
        for i, c in zip(self.indices, np.reshape(centers, (-1, 3)), strict=True):
            self.body.set_sphere_center(c, i)

    def acceleration(self, force: np.ndarray) -> np.ndarray:
        """Return ``a = g + F/m`` in the free components, 0 in the guided ones, (N, 3)."""
        return np.asarray(self.free * (self.gravity + force / self.mass[:, None]))

    def guide_force(self, force: np.ndarray) -> np.ndarray:
        """Return the guides' summed force on the balls [N]: ``-(m g + F)`` where guided."""
        total = (1.0 - self.free) * (self.mass[:, None] * self.gravity + force)
        return np.asarray(-total.sum(axis=0))

    def reactions(self) -> np.ndarray:
        """Force of each ball on the body ``R_i`` at the current state [N], (N, 3)."""
        return np.array([self.body.reaction_force(i) for i in self.indices])

    def ground_force(self) -> np.ndarray:
        """Return the force of the supports on the body [N]: other contacts and pins."""
        contacts = sum((self.body.reaction_force(i) for i in self.others), np.zeros(3))
        return np.asarray(contacts + self.body.pin_reaction())

    def body_momentum(self) -> np.ndarray:
        """``int rho v dX`` [kg m/s]."""
        return np.array([global_scalar(f) for f in self._momentum])

    def ball_momentum(self) -> np.ndarray:
        """``sum_i m_i w_i`` [kg m/s]."""
        return np.asarray(self.mass @ self.state.velocity, dtype=float)

    def stiffness(self, domains: dict[int, Any] | None = None) -> np.ndarray:
        """Block-diagonal ``dR/dc`` at fixed body [N/m], (3N, 3N).

        ``domains`` (:meth:`solvers.body.Body.contact_domains` at the current state)
        integrates each ball's stiffness over the facets that carry it, the same sums.
        """
        n = len(self.indices)
        K = np.zeros((3 * n, 3 * n))
        for b, forms in enumerate(self._stiffness):
            K[3 * b:3 * b + 3, 3 * b:3 * b + 3] = [
                [global_scalar(f if domains is None else with_facet_domains(f, domains))
                 for f in row] for row in forms]
        return K

    def interface_stiffness(self) -> np.ndarray:
        """``dR/dc`` of the balls against the body in equilibrium [N/m], (3N, 3N).

        ``K_c - G^T A^{-1} G`` (:meth:`stiffness` less :meth:`solvers.body.Body.
        obstacle_compliance` at the body's current state): the compliant body gives way
        under a moved sphere. Zero without contact (no body solve then). A compliance that
        is not positive semidefinite (the body's Jacobian is not positive definite, e.g. a
        buckling body) gives ``K_c`` itself, the stiffer secant the iteration started from
        before. Both are integrated over the facets that carry the obstacles' penalties at
        the current state (:meth:`solvers.body.Body.contact_domains`), the same sums as
        over every exterior facet.
        """
        domains = self.body.contact_domains()
        K = self.stiffness(domains)
        if not np.any(K):
            return K
        S = self.body.obstacle_compliance(self.indices, domains)
        if np.linalg.eigvalsh(S).min() < -1e-12 * np.abs(S).max():
            return K
        return np.asarray(K - S)

    def penetration(self) -> tuple[float, ...]:
        """``max(0, r - dist(c, surface)) / r`` of each ball [-] (collective)."""
        return tuple(self._surface.penetration(self.state.center, self.radius).tolist())

    # --- the coupled step -----------------------------------------------------------------------

    def step(self) -> RigidStepInfo:
        """Advance balls and body by ``body.options.dt`` (interface iteration, module doc).

        A step whose body solve fails, or whose interface iteration does not reach its
        tolerance, is redone as two coupled half steps, at most ``newton.max_halvings``
        deep: balls and body share every step size, so the impulses they exchange match and
        the ledger closes (a body halving alone would step the body but not the balls). The
        report sums the solves of the steps taken; ``halvings`` counts these halvings.

        Raises:
            SolverError: the last halving failed too; balls, ledger and body restored.

        """
        return self._halving_step(self.body.options.dt, self.body.newton.max_halvings)

    def _halving_step(self, h: float, budget: int) -> RigidStepInfo:
        """One coupled step of size ``h``, else two of ``h / 2`` with ``budget - 1`` left."""
        try:
            return self._step(h)  # on failure the body and the spheres are restored
        except SolverError:
            if budget <= 0:
                raise
        saved = (self.body.snapshot(), self.state.copy(), self.previous_acceleration.copy(),
                 copy.deepcopy(self.ledger))
        try:
            first = self._halving_step(0.5 * h, budget - 1)
            second = self._halving_step(0.5 * h, budget - 1)
        except SolverError:
            body_state, self.state, self.previous_acceleration, self.ledger = saved
            self.body.restore(body_state)
            self.set_centers(self.state.center)
            raise
        a, b = first.report, second.report
        report = dataclasses.replace(
            b, newton_iterations=a.newton_iterations + b.newton_iterations,
            halvings=1 + a.halvings + b.halvings, substeps=a.substeps + b.substeps)
        return RigidStepInfo(first.iterations + second.iterations,
                             max(first.mismatch, second.mismatch), second.penetration, report)

    def _step(self, h: float) -> RigidStepInfo:
        """One coupled step of size ``h`` (:meth:`step`), the body not halving on its own."""
        body, old = self.body, self.state
        self.set_centers(old.center)
        body.initial_acceleration()  # Newmark a_0 with the balls where they are
        saved = body.snapshot()
        beta, _, _ = scheme(self.dynamics)
        c_pred = predict(old, h, self.dynamics)
        scale = beta * h * h / np.repeat(self.mass, 3)
        last: dict[str, Any] = {}

        def residual(c: np.ndarray) -> np.ndarray:
            self.set_centers(c)
            guess = body.u.x.array.copy() if "report" in last else None  # the last solve's u
            body.restore(saved)
            report = body.step(guess, dt=h, max_halvings=0)
            if "report" in last:
                report = dataclasses.replace(report, **{
                    k: getattr(report, k) + getattr(last["report"], k)
                    for k in ("newton_iterations", "halvings")})
            last["report"] = report
            last["R"] = self.reactions()
            a = self.acceleration(-last["R"])
            return np.asarray(c - (c_pred + beta * h * h * a).reshape(-1))

        def jacobian(c: np.ndarray, r: np.ndarray) -> np.ndarray:
            free = self.free.reshape(-1)
            return np.eye(c.size) + (scale * free)[:, None] * self.interface_stiffness() * free

        a_guess = 2.0 * old.acceleration - self.previous_acceleration  # linear in time
        guess = (c_pred + beta * h * h * a_guess).reshape(-1)
        tol = self.options.coupling.rtol * float(self.radius.min())
        try:
            _, k, mismatch = broyden_solve(residual, guess, jacobian, tol,
                                           self.options.coupling.max_iterations)
        except np.linalg.LinAlgError:
            k, mismatch = 0, math.inf  # a singular secant Jacobian: report as not converged
        except SolverError:  # a body solve failed (the body restored itself)
            self.set_centers(old.center)
            raise
        if mismatch > tol:
            body.restore(saved)
            self.set_centers(old.center)
            raise SolverError(f"rigid coupling: ball position mismatch {mismatch:.3e} m > "
                              f"{tol:.3e} m after {k} body solves at t={body.t:.6g}")
        force = -last["R"]
        self.previous_acceleration = old.acceleration.copy()
        self.state = advance(old, c_pred, self.acceleration(force), force, h, self.dynamics)
        self._book(old, h)
        return RigidStepInfo(k, mismatch, self.penetration(), last["report"])

    def _book(self, old: BallState, h: float) -> None:
        """Add the step's contact and ground impulses to the ledger."""
        ground = self.ground_force()
        led = self.ledger
        led.contact_impulse += impulse(-old.force.sum(axis=0), -self.state.force.sum(axis=0),
                                       h, self.dynamics)
        led.ground_impulse += impulse(led.ground_force, ground, h, self.dynamics)
        led.ground_force = ground
        led.guide_impulse += impulse(self.guide_force(old.force),
                                     self.guide_force(self.state.force), h, self.dynamics)

    def balance(self) -> dict[str, list[float]]:
        """Momentum balance since the ledger's start (module docstring), (3,) lists [N s].

        ``ball_impulse`` (from the balls' momenta) and ``body_impulse`` (from the body's
        momentum, gravity and ground removed) should be opposite; ``contact_impulse`` is
        the bookkept ``sum h R``.
        """
        led, t = self.ledger, self.body.t - self.ledger.time0
        ball = (self.ball_momentum() - led.ball_momentum0 - self.mass.sum() * self.gravity * t
                - led.guide_impulse)
        body = (self.body_momentum() - led.body_momentum0 - self.body_mass * self.gravity * t
                - led.ground_impulse)
        return {"ball_impulse": ball.tolist(), "body_impulse": body.tolist(),
                "contact_impulse": led.contact_impulse.tolist(),
                "ground_impulse": led.ground_impulse.tolist(),
                "guide_impulse": led.guide_impulse.tolist()}

    # --- checkpoint -----------------------------------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        """Return the balls' state and ledger as named arrays (checkpoint stage ``rigid``)."""
        led = self.ledger
        return {"center": self.state.center, "velocity": self.state.velocity,
                "acceleration": self.state.acceleration, "force": self.state.force,
                "contact_impulse": led.contact_impulse, "ground_impulse": led.ground_impulse,
                "ground_force": led.ground_force, "body_momentum0": led.body_momentum0,
                "ball_momentum0": led.ball_momentum0, "guide_impulse": led.guide_impulse,
                "time0": np.array([led.time0]),
                "previous_acceleration": self.previous_acceleration}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """Set the balls' state and ledger from :meth:`arrays` (e.g. a checkpoint).

        Raises:
            InputError: an array is missing or of the wrong shape.

        """
        n = len(self.indices)
        try:
            state = [np.array(arrays[k], dtype=float).reshape(n, 3)
                     for k in ("center", "velocity", "acceleration", "force")]
            led = {k: np.array(arrays[k], dtype=float).reshape(3)
                   for k in ("contact_impulse", "ground_impulse", "ground_force",
                             "body_momentum0", "ball_momentum0", "guide_impulse")}
            time0 = float(np.asarray(arrays["time0"]).reshape(-1)[0])
            previous = np.array(arrays.get("previous_acceleration", state[2]),
                                dtype=float).reshape(n, 3)
        except (KeyError, ValueError) as exc:
            raise InputError(f"checkpoint: rigid ball state unusable ({exc})") from None
        self.state = BallState(*state)
        self.previous_acceleration = previous
        self.ledger = Ledger(**led, time0=time0)
        self.set_centers(self.state.center)


__all__ = ["Anderson", "BallCoupling", "CoupledFrame", "CouplingMode", "CouplingOptions",
           "CouplingScheme", "broyden_solve", "coupled_frame", "relative_change"]
