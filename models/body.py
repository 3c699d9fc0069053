"""The coarse body's scene description: discretisation, dynamics, loads, pins and contacts.

:class:`BodyOptions` and :class:`PinSpec` say *what* the body is (``[body]`` of a scene); the
incremental potential built from them and its time stepping are in :mod:`solvers.body`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from meshes.errors import InputError
from models.contact import ContactOptions, penalty_stiffness, vector3

DYNAMICS: tuple[str, ...] = ("static", "implicit_euler", "newmark")
NEWMARK_BETA: float = 0.25
NEWMARK_GAMMA: float = 0.5


@dataclass(frozen=True)
class PinSpec:
    """A set of nodes whose displacement components are prescribed.

    A node at reference position ``X`` is selected by the box ``box = (lo, hi)`` when
    ``lo - tol <= X <= hi + tol`` componentwise; without a box, by the plane through ``point``
    with ``normal`` when ``|(X - point).normal| <= tol``. Its components ``components`` follow
    the rigid motion that starts at rest,

        u(X, t) = (R(|w| t) - I)(X - point) + velocity t,

    with ``R(phi) = I + sin(phi) K + (1 - cos(phi)) K^2`` the rotation by ``phi`` about the unit
    axis ``a = w / |w|`` through ``point`` (Rodrigues; ``K v = a x v``), ``w`` the angular
    velocity vector. With ``w = 0`` (the default) the pin is a pure translation, with
    ``velocity = 0`` too a clamp. In statics ``t`` is the load parameter.

    Attributes:
        box: Lower and upper corners of the selection box [m]; ``None`` selects by the plane.
        point: A point of the plane, and of the rotation axis [m].
        normal: Normal of the plane (normalised here) [-].
        tol: Selection tolerance [m].
        components: Held displacement components (0 = x, 1 = y, 2 = z).
        velocity: Velocity of the pinned nodes [m/s] (per unit load parameter in statics).
        angular_velocity: Angular velocity vector ``w`` [rad/s] (per unit load parameter in
            statics); right-hand rule about ``w / |w|``.

    """

    box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    tol: float = 1.0e-8
    components: tuple[int, ...] = (0, 1, 2)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.box is not None:
            arr = np.asarray(self.box, dtype=float)
            if arr.shape != (2, 3) or np.any(np.isnan(arr)) or np.any(arr[0] > arr[1]):
                raise InputError(f"pin.box must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] "
                                 f"with min <= max, got {self.box!r}")
            object.__setattr__(self, "box", (tuple(float(a) for a in arr[0]),
                                             tuple(float(a) for a in arr[1])))
        for name in ("point", "normal", "velocity", "angular_velocity"):
            object.__setattr__(self, name, vector3(f"pin.{name}", getattr(self, name)))
        if self.box is None and np.linalg.norm(self.normal) == 0.0:
            raise InputError("pin.normal must be non-zero")
        if not (math.isfinite(self.tol) and self.tol >= 0.0):
            raise InputError(f"pin.tol must be >= 0, got {self.tol}")
        comps = tuple(int(c) for c in self.components)
        if not comps or any(c not in (0, 1, 2) for c in comps) or len(set(comps)) != len(comps):
            raise InputError(f"pin.components must be distinct values in 0, 1, 2, got "
                             f"{self.components!r}")
        object.__setattr__(self, "components", comps)

    @property
    def kind(self) -> str:
        """``"box"`` or ``"plane"``: how the pin selects its nodes."""
        return "plane" if self.box is None else "box"

    def describe(self) -> str:
        """Describe the selection in the scene's terms: its box or plane and ``tol`` [m]."""
        if self.box is None:
            where = f"the plane through {_point(self.point)} with normal {_point(self.normal)}"
        else:
            where = f"the box from {_point(self.box[0])} to {_point(self.box[1])}"
        return f"{where} (tol {self.tol:g} m)"

    def select(self, X: np.ndarray) -> np.ndarray:
        """Boolean mask of the rows of ``X`` ((n, 3) reference positions) that are pinned."""
        if self.box is None:
            n = np.asarray(self.normal) / np.linalg.norm(self.normal)
            return np.abs((X - np.asarray(self.point)) @ n) <= self.tol
        lo, hi = np.asarray(self.box[0]) - self.tol, np.asarray(self.box[1]) + self.tol
        return np.all((X >= lo) & (X <= hi), axis=1)

    def displacement(self, t: float) -> np.ndarray:
        """Prescribed translation ``velocity * t`` [m]."""
        return np.asarray(self.velocity) * t

    @property
    def rotates(self) -> bool:
        """True when the pin prescribes a rotation (``angular_velocity`` != 0)."""
        return bool(np.any(np.asarray(self.angular_velocity) != 0.0))

    def rotation(self, t: float) -> np.ndarray:
        """Rotation matrix ``R(|w| t)`` about ``w / |w|`` (Rodrigues), (3, 3)."""
        w = np.asarray(self.angular_velocity)
        rate = float(np.linalg.norm(w))
        if rate == 0.0:
            return np.eye(3)
        a, phi = w / rate, rate * t
        K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
        return np.eye(3) + math.sin(phi) * K + (1.0 - math.cos(phi)) * (K @ K)

    def displacement_at(self, X: np.ndarray, t: float) -> np.ndarray:
        """Prescribed displacement ``(R - I)(X - point) + velocity t`` of rows X [m]."""
        arm = np.asarray(X, dtype=float).reshape(-1, 3) - np.asarray(self.point)
        return arm @ (self.rotation(t) - np.eye(3)).T + self.displacement(t)


CONFLICT_TIMES: tuple[float, ...] = (0.37, 1.0, 2.9)
"""Times (load parameters) at which two pins' motions of a shared node are compared: affine
and rotational motions that agree at three generic times are the same motion."""


@dataclass(frozen=True)
class PinConflict:
    """Two pins holding the same component of shared nodes to different motions.

    Attributes:
        first: Index of the first pin in ``BodyOptions.pins``.
        second: Index of the second pin.
        component: The displacement component both hold (0 = x, 1 = y, 2 = z).
        nodes: Indices of the shared nodes whose motions differ (rows of the positions).

    """

    first: int
    second: int
    component: int
    nodes: np.ndarray


def pin_conflicts(pins: tuple[PinSpec, ...] | list[PinSpec], X: np.ndarray,
                  times: tuple[float, ...] = CONFLICT_TIMES) -> list[PinConflict]:
    """Every pair of pins that prescribe different displacements of a shared node's component.

    A node held by two pins gets whichever Dirichlet value is applied last; equal motions
    (two clamps meeting at an edge) are fine, different ones are an error of the scene. The
    displacements ``displacement_at(X, t)`` are compared at ``times`` to within ``1e-12`` of
    the positions' extent.

    Args:
        pins: The pins, in the scene's order.
        X: Reference positions of the nodes, (n, 3) [m].
        times: Times of the comparison.

    """
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    tol = 1e-12 * max(1.0, float(np.abs(X).max(initial=0.0)))
    masks = [pin.select(X) for pin in pins]
    out: list[PinConflict] = []
    for i, a in enumerate(pins):
        for j in range(i + 1, len(pins)):
            b, shared = pins[j], np.flatnonzero(masks[i] & masks[j])
            for k in sorted(set(a.components) & set(b.components)) if shared.size else ():
                differ = np.zeros(shared.size, dtype=bool)
                for t in times:
                    diff = a.displacement_at(X[shared], t)[:, k] - b.displacement_at(
                        X[shared], t)[:, k]
                    differ |= np.abs(diff) > tol
                if differ.any():
                    out.append(PinConflict(i, j, k, shared[differ]))
    return out


def refuse_empty_pins(pins: Sequence[PinSpec], counts: Sequence[int],
                      span: tuple[np.ndarray, np.ndarray]) -> None:
    """Raise InputError naming the first pin that holds no node.

    Args:
        pins: The pins, in the scene's order.
        counts: Nodes each pin holds.
        span: Smallest and largest reference coordinates of the mesh's nodes, (3,) each [m]:
            the message gives them, so that a region drawn for another frame or scale shows.

    """
    for index, (pin, count) in enumerate(zip(pins, counts, strict=True)):
        if count == 0:
            lo, hi = (np.asarray(a, dtype=float) for a in span)
            extent = float(max(np.abs(lo).max(), np.abs(hi).max()))
            lo, hi = _rounded(lo, extent), _rounded(hi, extent)
            ranges = ", ".join(f"{axis} {a:.4g} .. {b:.4g}"
                               for axis, a, b in zip("xyz", lo, hi, strict=True))
            raise InputError(f"body.pins[{index}]: {pin.describe()} selects no node of the "
                             f"mesh, whose nodes span {ranges} m")


def _point(v: Sequence[float] | np.ndarray) -> str:
    """``(x, y, z)`` to four significant digits."""
    return "(" + ", ".join(f"{float(c):.4g}" for c in v) + ")"


def _rounded(v: np.ndarray, extent: float) -> np.ndarray:
    """``v`` with the coordinates within ``1e-12 max(1, extent)`` of 0 printed as 0."""
    return np.where(np.abs(v) <= 1e-12 * max(1.0, extent), 0.0, v)


def refuse_pin_conflicts(found: Sequence[tuple[int, int, int, np.ndarray]],
                         extent: float) -> None:
    """Raise InputError naming the first conflict of ``found``; nothing when it is empty.

    Args:
        found: ``(first, second, component, positions)`` per conflict
            (:func:`pin_conflicts`, the shared nodes' reference positions (m, 3) [m]),
            gathered from every rank.
        extent: Largest absolute coordinate of the mesh [m]: coordinates within ``1e-12`` of
            it are printed as 0.

    Raises:
        InputError: naming ``body.pins[i]`` and ``body.pins[j]``, the component, how many
            nodes they share there and the first node's position.

    """
    if not found:
        return
    i, j, k, nodes = found[0]
    count = sum(len(n) for (a, b, c, n) in found if (a, b, c) == (i, j, k))
    raise InputError(f"body.pins[{i}] and body.pins[{j}] both hold {count} node(s) (the first "
                     f"at {_point(_rounded(nodes[0], extent))} m) in component {'xyz'[k]} with "
                     "different motions; leave the shared nodes to one pin (narrow its box or "
                     "tol, or its components) or move them alike")


RIGID_MOTIONS: tuple[str, ...] = ("translation along x", "translation along y",
                                  "translation along z", "rotation about x", "rotation about y",
                                  "rotation about z")
"""The columns of :func:`rigid_motion_gram`, in its order."""


def held_components(pins: Sequence[PinSpec], X: np.ndarray) -> np.ndarray:
    """``(n, 3)`` mask: component ``k`` of node ``i`` (reference position ``X[i]``) is held."""
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    held = np.zeros(X.shape, dtype=bool)
    for pin in pins:
        held[np.ix_(pin.select(X), list(pin.components))] = True
    return held


def rigid_motion_gram(held: np.ndarray, X: np.ndarray, center: np.ndarray,
                      length: float) -> np.ndarray:
    """Gram matrix ``C^T C`` of the rigid motions' held components, (6, 6).

    ``C`` has a row per held (node ``i``, component ``k``) and a column per rigid motion of
    :data:`RIGID_MOTIONS`: component ``k`` at ``X_i`` of the translation ``e_j`` or of the
    rotation ``e_j x (X_i - center) / length``. A rigid motion ``m`` the pins leave free has
    ``C m = 0`` (a static body's Newton systems are then singular). A sum over nodes: the
    ranks' matrices of their owned nodes add up to the whole body's.

    Args:
        held: :func:`held_components` of the nodes.
        X: Their reference positions, (n, 3) [m].
        center: Point the rotations are about [m] (the held nodes' centroid names them best).
        length: Length scale of the rotations' columns [m] (> 0).

    """
    r = (np.asarray(X, dtype=float).reshape(-1, 3) - np.asarray(center)) / length
    gram = np.zeros((6, 6))
    for k in range(3):
        rows = r[held[:, k]]
        c = np.zeros((rows.shape[0], 6))
        c[:, k] = 1.0
        for j in range(3):  # (e_j x r)_k = eps_{k j l} r_l
            c[:, 3 + j] = np.cross(np.eye(3)[j], rows)[:, k]
        gram += c.T @ c
    return gram


def free_rigid_motions(gram: np.ndarray, rtol: float = 1e-10) -> tuple[int, list[str]]:
    """How many rigid motions ``gram`` leaves free, and which of :data:`RIGID_MOTIONS` are.

    The count is that of the eigenvalues of ``gram`` at most ``rtol max(1, lambda_max)``; a
    named motion has its own column's norm ``gram[j, j]`` that small (a free combination of
    several, e.g. a rotation about an axis away from ``center``, counts but is not named).
    """
    limit = rtol * max(1.0, float(np.abs(gram).max()))
    count = int(np.count_nonzero(np.linalg.eigvalsh(gram) <= limit))
    return count, [name for j, name in enumerate(RIGID_MOTIONS) if gram[j, j] <= limit]


@dataclass(frozen=True)
class BodyOptions:
    """Discretisation, time integration, loads and boundary conditions of the body.

    Attributes:
        degree: Lagrange degree of the displacement, 1 (P1) or 2 (P2).
        dynamics: ``"static"``, ``"implicit_euler"`` or ``"newmark"`` (beta 1/4, gamma 1/2).
        dt: Time step [s] (load-parameter increment in statics), > 0.
        gravity: Gravitational acceleration [m/s^2].
        pins: Prescribed-displacement sets.
        contacts: Rigid obstacles with penalty contact.
        contact_stiffness: Penalty stiffness of every contact of the body (obstacles and rigid
            balls) [Pa/m]; ``None`` means ``100 E / h_min``
            (:func:`models.contact.penalty_stiffness`).

    """

    degree: int = 1
    dynamics: str = "static"
    dt: float = 1.0e-2
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    pins: tuple[PinSpec, ...] = ()
    contacts: tuple[ContactOptions, ...] = ()
    contact_stiffness: float | None = None

    def __post_init__(self) -> None:
        if self.degree not in (1, 2):
            raise InputError(f"body.degree must be 1 or 2, got {self.degree}")
        if self.dynamics not in DYNAMICS:
            raise InputError(f"body.dynamics must be one of {DYNAMICS}, got {self.dynamics!r}")
        if not (math.isfinite(self.dt) and self.dt > 0.0):
            raise InputError(f"body.dt must be > 0, got {self.dt}")
        object.__setattr__(self, "gravity", vector3("body.gravity", self.gravity))
        object.__setattr__(self, "pins", tuple(_as(PinSpec, p) for p in self.pins))
        object.__setattr__(self, "contacts", tuple(_as(ContactOptions, c)
                                                   for c in self.contacts))
        if self.contact_stiffness is not None:
            penalty_stiffness(self.contact_stiffness, 1.0, 1.0)  # validates

    @property
    def qdegree(self) -> int:
        """Degree of the volume quadrature, ``2 * degree``.

        Exact for the mass matrix and the linearised stiffness of P1 and P2; the inertia,
        load and contact-free volume terms and the det F checks use it, the strain energy
        :meth:`elastic_qdegree`.
        """
        return 2 * self.degree

    def elastic_qdegree(self, affine: bool) -> int:
        """Degree of the quadrature of the strain energy ``int psi(F) dX``.

        On an affine P1 tetrahedron ``F = I + grad u`` is constant, so ``psi(F)`` is and one
        point (degree 0) integrates it, its gradient and its Hessian exactly; otherwise (P2
        or curved cells) :attr:`qdegree`.
        """
        return 0 if self.degree == 1 and affine else self.qdegree


def _as(cls: type, value: Any) -> Any:
    """``value`` if it is a ``cls`` already, else ``cls(**value)`` (a TOML table)."""
    return value if isinstance(value, cls) else cls(**dict(value))
