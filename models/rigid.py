"""Rigid balls coupled two-way to the elastic body through the penalty contact of contact.py.

A ball of mass ``m``, radius ``r``, centre ``c`` and velocity ``w`` obeys ``m dw/dt = m g + F``
with ``F = -R`` and ``R = int_dOmega -k <g>_- grad g dA`` the force the ball's sphere obstacle
exerts on the body (:class:`models.contact.PenaltyContact`, ``Body.reaction_force``): the
contact force on the ball is minus the assembled reaction on the body (Newton's third law
holds exactly because both come from the same integral).

Time integration: the ball uses the body's scheme (Newmark family, ``a = dw/dt``), so ball
and body share one time-discrete momentum balance:

    implicit Euler (beta = gamma = 1):  c_pred = c_n + h w_n
    Newmark (beta = 1/4, gamma = 1/2):   c_pred = c_n + h w_n + h^2 (1/2 - beta) a_n
    both:  c_{n+1} = c_pred + beta h^2 a_{n+1},  w_{n+1} = w_n + h ((1-gamma) a_n + gamma a_{n+1}),
           a_{n+1} = g - R_{n+1} / m.

Two-way coupling within a step (iterated by :class:`solvers.coupling.BallCoupling`). Ball
and body together minimise one incremental potential
``Pi_body(u; c) + m/(2 beta h^2) |c - c_pred|^2 - m g.c``; the contact energy couples ``u``
and ``c``. A plain explicit staggering (move the ball with the previous step's force, then solve the
body) is only conditionally stable: its error is amplified by ``beta h^2 K / m`` per step (``K ~
k * contact area``, >> 1 for stiff penalties). Here each step instead solves the interface
equation

    r(c) = c - c_pred - beta h^2 (g - R(c, u(c)) / m) = 0,

where ``u(c)`` is the body's converged step with the sphere at ``c``, by Broyden's method
(Broyden 1965; Degroote et al. 2009) until ``max |r| <= rtol * radius``, from the guess
``c_pred + beta h^2 (2 a_n - a_{n-1})`` with ``J_0 = I + beta h^2 (K_c - G^T A^{-1} G) / m``
at the body solved there (a Newton step: ``K_c = dR/dc`` at fixed body less the body's give,
:meth:`PenaltyContact.center_coupling_forms`). Momentum bookkeeping: :class:`Ledger`.

A guided ball (``RigidBallOptions.guide``) is held in the guided components (a = w = 0; the
guide's reaction ``-(m g + F)`` there is booked as ``guide``).

Not modelled: friction, rotation of the balls, ball-ball contact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from meshes.errors import InputError
from models.backend import MPI
from models.contact import (
    BoundaryTriangles,
    ContactOptions,
    exterior_facets,
    point_triangle_distance,
    vector3,
)

SCHEMES: dict[str, tuple[float, float, float]] = {
    "implicit_euler": (1.0, 1.0, 0.0),
    "newmark": (0.25, 0.5, 0.25),
}
"""dynamics -> (beta, gamma, weight of a_n in the predictor ``h^2 (1/2 - beta)``)."""


@dataclass(frozen=True)
class RigidBallOptions:
    """A rigid sphere; its gravity is the body's (``body.gravity``), its scheme the body's.

    Its contact with the body is a sphere obstacle (:meth:`contact`) with the body's penalty
    stiffness (``body.contact_stiffness``).

    Attributes:
        radius: Radius [m] (> 0).
        mass: Mass [kg] (> 0; required).
        center: Centre at t = 0 [m].
        velocity: Velocity at t = 0 [m/s].
        guide: Components (0 = x, 1 = y, 2 = z) of the ball's motion held by a frictionless
            guide, e.g. ``[0, 1]``: the ball moves only vertically. Frictionless contact gives
            a sphere no torque and a flat cushion no horizontal restoring force, so without a
            guide the slight asymmetry of a coarse mesh's dent sets the ball sliding sideways
            for ever. The guide's reaction is booked in the :class:`Ledger`.

    """

    radius: float = 0.1
    mass: float | None = None
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    guide: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        guide = tuple(int(k) for k in self.guide)
        if any(k not in (0, 1, 2) for k in guide) or len(set(guide)) != len(guide):
            raise InputError(f"ball.guide must be distinct values in 0, 1, 2, got {self.guide!r}")
        object.__setattr__(self, "guide", guide)
        if self.mass is None:
            raise InputError("ball.mass: missing (the ball's mass [kg])")
        if not (math.isfinite(self.mass) and self.mass > 0.0):
            raise InputError(f"ball.mass must be > 0, got {self.mass}")
        object.__setattr__(self, "center", vector3("ball.center", self.center))
        object.__setattr__(self, "velocity", vector3("ball.velocity", self.velocity))
        if any(self.velocity[k] != 0.0 for k in guide):
            raise InputError(f"ball.velocity must be 0 in the guided components {guide}, got "
                             f"{self.velocity}")
        self.contact()  # validates the radius

    @property
    def free(self) -> np.ndarray:
        """1.0 for the components the ball moves in, 0.0 for the guided ones, (3,)."""
        mask = np.ones(3)
        mask[list(self.guide)] = 0.0
        return mask

    def contact(self) -> ContactOptions:
        """Return the sphere obstacle that holds the ball off the body."""
        try:
            return ContactOptions(obstacle="sphere", point=self.center, radius=self.radius)
        except InputError as exc:
            raise InputError(str(exc).replace("contact.", "ball.")) from None


@dataclass(frozen=True)
class RigidCouplingOptions:
    """The per-step interface iteration ball position <-> body solve (``[rigid] options``).

    Attributes:
        rtol: Stop when ``max |r(c)| <= rtol * radius`` (r: mismatch of the ball position
            with the integrator's update for the force of the body solve) [-].
        max_iterations: Body solves per step at most; more raise ``SolverError``.

    """

    rtol: float = 1.0e-8
    max_iterations: int = 30

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rtol) and self.rtol > 0.0):
            raise InputError(f"options.rtol must be > 0, got {self.rtol}")
        if self.max_iterations < 1:
            raise InputError(f"options.max_iterations must be >= 1, got {self.max_iterations}")


@dataclass(frozen=True)
class RigidOptions:
    """The scene's rigid bodies (``[rigid]`` table with ``[[rigid.balls]]`` entries).

    Attributes:
        balls: The rigid balls; each adds a sphere contact to the body.
        coupling: The per-step coupling iteration.

    """

    balls: tuple[RigidBallOptions, ...] = ()
    coupling: RigidCouplingOptions = field(default_factory=RigidCouplingOptions)

    def __post_init__(self) -> None:
        balls = tuple(b if isinstance(b, RigidBallOptions) else RigidBallOptions(**dict(b))
                      for b in self.balls)
        object.__setattr__(self, "balls", balls)


# --------------------------------------------------------------------------------------------
# The integrator (pure numpy)


def scheme(dynamics: str) -> tuple[float, float, float]:
    """``(beta, gamma, predictor weight of a_n)`` of the body's dynamics (module docstring)."""
    if dynamics not in SCHEMES:
        raise InputError(f"rigid balls need body.dynamics in {tuple(SCHEMES)}, got "
                         f"{dynamics!r}")
    return SCHEMES[dynamics]


@dataclass
class BallState:
    """Centres, velocities, accelerations and contact forces of ``N`` balls, arrays (N, 3).

    Attributes:
        center: Centres [m].
        velocity: Velocities [m/s].
        acceleration: Accelerations ``g + F/m`` [m/s^2].
        force: Contact force on each ball ``F = -R`` at the current time [N].

    """

    center: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    force: np.ndarray

    def copy(self) -> BallState:
        """Return a deep copy."""
        return BallState(*(np.array(a, copy=True) for a in self.arrays()))

    def arrays(self) -> tuple[np.ndarray, ...]:
        """``(center, velocity, acceleration, force)``."""
        return self.center, self.velocity, self.acceleration, self.force


def predict(state: BallState, h: float, dynamics: str) -> np.ndarray:
    """Predicted centres ``c_pred = c_n + h w_n + h^2 (1/2 - beta) a_n`` (Newmark term only)."""
    _, _, weight = scheme(dynamics)
    return state.center + h * state.velocity + h * h * weight * state.acceleration


def advance(state: BallState, c_pred: np.ndarray, accel: np.ndarray, force: np.ndarray,
            h: float, dynamics: str) -> BallState:
    """Return the state at ``t + h`` given the new acceleration ``a_{n+1}`` and contact force."""
    beta, gamma, _ = scheme(dynamics)
    velocity = state.velocity + h * ((1.0 - gamma) * state.acceleration + gamma * accel)
    return BallState(c_pred + beta * h * h * accel, velocity, accel.copy(), force.copy())


def impulse(old: np.ndarray, new: np.ndarray, h: float, dynamics: str) -> np.ndarray:
    """Impulse ``h ((1 - gamma) F_n + gamma F_{n+1})`` of a force over a step [N s]."""
    _, gamma, _ = scheme(dynamics)
    return h * ((1.0 - gamma) * np.asarray(old) + gamma * np.asarray(new))


# --------------------------------------------------------------------------------------------
# Two-way coupling with the body


def initial_state(balls: tuple[RigidBallOptions, ...], gravity: np.ndarray) -> BallState:
    """Balls at their initial centres and velocities, free-fall acceleration, no force."""
    n = len(balls)
    free = np.array([b.free for b in balls]).reshape(n, 3)
    return BallState(np.array([b.center for b in balls], dtype=float).reshape(n, 3),
                     np.array([b.velocity for b in balls], dtype=float).reshape(n, 3),
                     free * gravity, np.zeros((n, 3)))


@dataclass
class Ledger:
    """Cumulative momentum bookkeeping since t = 0 (all (3,) vectors, SI units).

    The ball's velocity is updated with the *same*
    ``R_{n+1}`` that the body's last solve felt (the last iterate), so the momentum exchanged is
    exact up to the body's Newton tolerance even when the interface iteration stops at its
    tolerance (the position mismatch ``|r|`` is the only inexactness). Per step the impulse of a
    force is ``h ((1 - gamma) F_n + gamma F_{n+1})``, the scheme's own quadrature; the body's
    discrete momentum ``P = int rho v dX`` changes by ``M g h`` + the impulses of all its contacts
    (test function = a constant vector, the partition of unity). So

        impulse on the balls  = m (w - w_0) - m g t - guide  = - sum_steps h R
        impulse on the body   = P - P_0 - M g t - ground     = + sum_steps h R

    and their sum is zero to solver tolerance. "Ground" is every support of the body: its other
    contacts (``Body.reaction_force``) and its pins (``Body.pin_reaction``, the residual at the
    pinned dofs).

    Attributes:
        contact_impulse: Impulse of the balls' contacts on the body ``sum h R`` [N s]
            (the balls receive minus it).
        ground_impulse: Impulse of the supports (other contacts, pins) on the body [N s].
        ground_force: Force of the supports on the body at the current time [N].
        guide_impulse: Impulse of the balls' guides on the balls [N s] (``guide``).
        body_momentum0: Body momentum ``int rho v dX`` at t = 0 [kg m/s].
        ball_momentum0: Summed ball momentum at t = 0 [kg m/s].
        time0: Time of the state the ledger starts from [s].

    """

    contact_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ground_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ground_force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    body_momentum0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ball_momentum0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    guide_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time0: float = 0.0


@dataclass(frozen=True)
class RigidStepInfo:
    """What one coupled step did.

    Attributes:
        iterations: Body solves of the interface iteration.
        mismatch: Final ``max |r|`` [m].
        penetration: Penetration of each ball into the body, fraction of its radius.
        report: The body's step report of the last solve, with ``newton_iterations`` and
            ``halvings`` summed over all the step's body solves.

    """

    iterations: int
    mismatch: float
    penetration: tuple[float, ...]
    report: Any


class BoundaryFacets:
    """The body's exterior triangles (P1 geometry of the deformed vertices) on this rank.

    Penetration of a sphere ``(c, r)`` is ``max(0, r - min_T dist(c, T)) / r`` over the
    triangles ``T``: the depth of the deepest point of the piecewise-linear surface inside
    the ball (exact for P1; the vertices of P2 facets for P2). Valid while ``c`` is outside
    the body.
    """

    def __init__(self, body: Any) -> None:
        self.surface = BoundaryTriangles.of(body.mesh, body.V, exterior_facets(body.mesh))
        self.body, self.comm = body, body.mesh.comm

    def triangles(self) -> np.ndarray:
        """Deformed triangles (m, 3, 3) [m]."""
        return self.surface.deformed(self.body.u.x.array)

    def penetration(self, centers: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """Penetration of each sphere as a fraction of its radius (collective) [-], (N,).

        The deformed triangles are gathered once for all ``N`` spheres (``centers`` (N, 3),
        ``radii`` (N,)), and one ``MPI.MIN`` reduction gives every distance.
        """
        tri = self.triangles()
        local = np.array([point_triangle_distance(c, tri).min() if len(tri) else math.inf
                          for c in np.reshape(centers, (-1, 3))])
        dist = np.empty_like(local)
        self.comm.Allreduce(local, dist, op=MPI.MIN)
        return np.asarray(np.maximum(0.0, radii - dist) / radii)


__all__ = ["BallState", "Ledger", "RigidBallOptions", "RigidCouplingOptions",
           "RigidOptions", "RigidStepInfo", "advance", "impulse",
           "initial_state", "predict", "scheme"]
