"""The coarse body's scene description: discretisation, dynamics, loads, pins and contacts.

:class:`BodyOptions` and :class:`PinSpec` say *what* the body is (``[body]`` of a scene); the
incremental potential built from them and its time stepping are in :mod:`solvers.body`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from meshes.errors import InputError
from models.contact import ContactOptions, vector3

DYNAMICS: tuple[str, ...] = ("static", "implicit_euler", "newmark")
NEWMARK_BETA: float = 0.25
NEWMARK_GAMMA: float = 0.5


@dataclass(frozen=True)
class PinSpec:
    """A set of nodes whose displacement components are prescribed.

    A node at reference position ``X`` is selected by a box when
    ``box_min - tol <= X <= box_max + tol`` componentwise, by a plane when
    ``|(X - point).normal| <= tol``. Its components ``components`` are held at

        u(X, t) = (R(phi(t)) - I)(X - center) + value + velocity t,   phi = angle + omega t,

    a rigid motion: ``R(phi) = I + sin(phi) K + (1 - cos(phi)) K^2`` is the rotation by
    ``phi`` about the unit ``axis`` through ``center`` (Rodrigues; ``K a = axis x a``). With
    ``angle = omega = 0`` (the default) the pin is a pure translation.

    Attributes:
        kind: ``"box"`` or ``"plane"``.
        box_min: Lower corner of the box [m].
        box_max: Upper corner of the box [m].
        point: A point of the plane [m].
        normal: Normal of the plane (normalised here) [-].
        tol: Selection tolerance [m].
        components: Held displacement components (0 = x, 1 = y, 2 = z).
        value: Prescribed displacement at t = 0 [m].
        velocity: Prescribed velocity of the pinned nodes [m/s] (per unit load parameter in
            statics).
        axis: Rotation axis (normalised here; non-zero when the pin rotates) [-].
        center: A point of the rotation axis [m].
        angle: Rotation angle at t = 0 [rad].
        angular_velocity: Angular velocity ``omega`` about ``axis`` [rad/s] (per unit load
            parameter in statics); right-hand rule.

    """

    kind: str = "box"
    box_min: tuple[float, float, float] = (-math.inf, -math.inf, -math.inf)
    box_max: tuple[float, float, float] = (math.inf, math.inf, math.inf)
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    tol: float = 1.0e-8
    components: tuple[int, ...] = (0, 1, 2)
    value: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angle: float = 0.0
    angular_velocity: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("box", "plane"):
            raise InputError(f"pin.kind must be 'box' or 'plane', got {self.kind!r}")
        for name in ("box_min", "box_max"):
            arr = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if arr.shape != (3,) or np.any(np.isnan(arr)):
                raise InputError(f"pin.{name} must be a 3-vector, got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(float(a) for a in arr))
        for name in ("point", "normal", "value", "velocity", "axis", "center"):
            object.__setattr__(self, name, vector3(f"pin.{name}", getattr(self, name)))
        for name in ("angle", "angular_velocity"):
            if not math.isfinite(float(getattr(self, name))):
                raise InputError(f"pin.{name} must be finite, got {getattr(self, name)!r}")
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.rotates and np.linalg.norm(self.axis) == 0.0:
            raise InputError("pin.axis must be non-zero for a rotating pin")
        if self.kind == "plane" and np.linalg.norm(self.normal) == 0.0:
            raise InputError("pin.normal must be non-zero")
        if not (math.isfinite(self.tol) and self.tol >= 0.0):
            raise InputError(f"pin.tol must be >= 0, got {self.tol}")
        comps = tuple(int(c) for c in self.components)
        if not comps or any(c not in (0, 1, 2) for c in comps) or len(set(comps)) != len(comps):
            raise InputError(f"pin.components must be distinct values in 0, 1, 2, got "
                             f"{self.components!r}")
        object.__setattr__(self, "components", comps)

    def select(self, X: np.ndarray) -> np.ndarray:
        """Boolean mask of the rows of ``X`` ((n, 3) reference positions) that are pinned."""
        if self.kind == "plane":
            n = np.asarray(self.normal) / np.linalg.norm(self.normal)
            return np.abs((X - np.asarray(self.point)) @ n) <= self.tol
        lo, hi = np.asarray(self.box_min) - self.tol, np.asarray(self.box_max) + self.tol
        return np.all((X >= lo) & (X <= hi), axis=1)

    def displacement(self, t: float) -> np.ndarray:
        """Prescribed displacement ``value + velocity * t`` [m]."""
        return np.asarray(self.value) + np.asarray(self.velocity) * t

    @property
    def rotates(self) -> bool:
        """True when the pin prescribes a rotation (``angle`` or ``angular_velocity`` != 0)."""
        return self.angle != 0.0 or self.angular_velocity != 0.0

    def rotation(self, t: float) -> np.ndarray:
        """Rotation matrix ``R(angle + omega t)`` about ``axis`` (Rodrigues), (3, 3)."""
        a = np.asarray(self.axis) / np.linalg.norm(self.axis)
        phi = self.angle + self.angular_velocity * t
        K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
        return np.eye(3) + math.sin(phi) * K + (1.0 - math.cos(phi)) * (K @ K)

    def displacement_at(self, X: np.ndarray, t: float) -> np.ndarray:
        """Prescribed displacement ``(R - I)(X - center) + value + velocity t`` of rows X [m]."""
        arm = np.asarray(X, dtype=float).reshape(-1, 3) - np.asarray(self.center)
        return arm @ (self.rotation(t) - np.eye(3)).T + self.displacement(t)


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
        quadrature_degree: Degree of the volume quadrature; ``None`` means ``2 * degree``.

    """

    degree: int = 1
    dynamics: str = "static"
    dt: float = 1.0e-2
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    pins: tuple[PinSpec, ...] = ()
    contacts: tuple[ContactOptions, ...] = ()
    quadrature_degree: int | None = None

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
        if self.quadrature_degree is not None and self.quadrature_degree < 1:
            raise InputError(f"body.quadrature_degree must be >= 1, got "
                             f"{self.quadrature_degree}")

    @property
    def qdegree(self) -> int:
        """The volume quadrature degree in use."""
        return self.quadrature_degree or 2 * self.degree


def _as(cls: type, value: Any) -> Any:
    """``value`` if it is a ``cls`` already, else ``cls(**value)`` (a TOML table)."""
    return value if isinstance(value, cls) else cls(**dict(value))
