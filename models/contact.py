"""Penalty contact of the body with rigid obstacles (ground plane, sphere) as UFL energy terms.

For a rigid obstacle with signed gap function ``g(x)`` (> 0 outside, < 0 inside) evaluated at
the current position ``x = X + u`` of a boundary point, the penalty energy is

    Pi_c(u) = int_{dOmega_0} k/2 <g(X + u)>_-^2 dA,    <g>_- = min(g, 0),

(Wriggers, "Computational Contact Mechanics", 2006, sec. 6.3: the quadratic penalty is the
classic C^1 choice; it enters the Newton Jacobian through ``ufl.derivative``). The traction on
the body is ``t = -k <g>_- grad g`` and the force the obstacle exerts on the body is the
assembled vector integral ``R = int -k <g>_- grad g dA``; the force on the obstacle is ``-R``.

Gap functions (``n`` unit normal pointing out of the obstacle):
    plane through ``p``:            g = (x - p).n,           grad g = n
    sphere of centre c, radius r:   g = |x - c| - r,         grad g = (x - c)/|x - c|

The penalty stiffness ``k`` [Pa/m] defaults to ``100 E / h`` with ``h`` the smallest cell
diameter of the mesh, so the penetration under a pressure ``p`` is ``p h / (100 E)``, a small
fraction of a cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from meshes.errors import InputError
from models.backend import MPI, dolfinx, exterior_facet_domain, ufl

OBSTACLES: tuple[str, ...] = ("plane", "sphere")
"""Obstacle shapes."""
FACET_QUADRATURE: dict[str, int] = {"plane": 4, "sphere": 6}
"""Facet quadrature degree of the penalty per obstacle: the integrand has a kink at g = 0, so
more points than the polynomial degree help; a curved obstacle's dent is narrower, so more
points keep the penetration between them small."""
DEFAULT_STIFFNESS_FACTOR: float = 100.0
"""Default penalty stiffness in units of ``E / h_min`` (module docstring)."""


def vector3(name: str, value: Any) -> tuple[float, float, float]:
    """Return a finite 3-vector as a tuple of floats, or raise InputError naming ``name``."""
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be a finite 3-vector, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class ContactOptions:
    """A rigid obstacle held off the body by a penalty energy.

    The facet quadrature has :data:`FACET_QUADRATURE` points per obstacle shape, the penalty
    stiffness is the body's (``body.contact_stiffness``, :func:`penalty_stiffness`).

    Attributes:
        obstacle: ``"plane"`` (ground) or ``"sphere"``.
        point: A point of the plane, or the centre of the sphere at t = 0 [m]
            (``Body.set_sphere_center`` moves a sphere between steps).
        normal: Normal of the plane pointing to the free side (normalised here) [-].
        radius: Radius of the sphere [m] (> 0; sphere only).

    """

    obstacle: str = "plane"
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    radius: float = 1.0

    def __post_init__(self) -> None:
        if self.obstacle not in OBSTACLES:
            raise InputError(f"contact.obstacle must be one of {OBSTACLES}, got {self.obstacle!r}")
        object.__setattr__(self, "point", vector3("contact.point", self.point))
        normal = np.asarray(vector3("contact.normal", self.normal))
        if np.linalg.norm(normal) == 0.0:
            raise InputError("contact.normal must be non-zero")
        object.__setattr__(self, "normal", vector3("contact.normal",
                                                    normal / np.linalg.norm(normal)))
        if not (math.isfinite(self.radius) and self.radius > 0.0):
            raise InputError(f"contact.radius must be > 0, got {self.radius}")

    @property
    def quadrature_degree(self) -> int:
        """Degree of the facet quadrature of the penalty (:data:`FACET_QUADRATURE`)."""
        return FACET_QUADRATURE[self.obstacle]

    def gap_at(self, points: np.ndarray) -> np.ndarray:
        """Signed gap of ``points`` ((n, 3) [m]) at t = 0: ``(x - p).n`` or ``|x - c| - r``."""
        x = np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(self.point)
        if self.obstacle == "plane":
            return np.asarray(x @ np.asarray(self.normal))
        return np.asarray(np.linalg.norm(x, axis=1) - self.radius)

    def start_depth(self, points: np.ndarray) -> tuple[float, int]:
        """Deepest of ``points`` inside the obstacle at t = 0 [m], and how many are inside.

        A gap within round-off of zero (``1e-12`` of the largest coordinate, radius or
        obstacle point, at least of 1 m) counts as touching, not inside: a mesh whose bottom
        lies on the floor's plane starts clear of it.
        """
        x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        gaps = self.gap_at(x)
        scale = max(1.0, float(np.abs(x).max(initial=0.0)), float(np.abs(self.point).max()),
                    self.radius if self.obstacle == "sphere" else 0.0)
        inside = gaps < -1e-12 * scale
        return (float(-gaps[inside].min()) if inside.any() else 0.0, int(inside.sum()))

    def describe(self) -> str:
        """``plane through [p] with normal [n]`` or ``sphere at [c] of radius r``."""
        if self.obstacle == "plane":
            return f"plane through {list(self.point)} with normal {list(self.normal)}"
        return f"sphere at {list(self.point)} of radius {self.radius:g}"


def penalty_stiffness(stiffness: float | None, young: float, h_min: float) -> float:
    """Penalty stiffness ``k`` [Pa/m]: ``stiffness``, or ``DEFAULT_STIFFNESS_FACTOR E / h_min``.

    Raises:
        InputError: a given ``stiffness`` that is not finite and > 0.

    """
    if stiffness is None:
        return DEFAULT_STIFFNESS_FACTOR * young / h_min
    if not (math.isfinite(stiffness) and stiffness > 0.0):
        raise InputError(f"body.contact_stiffness must be > 0, got {stiffness}")
    return float(stiffness)


def exterior_facets(mesh: Any) -> np.ndarray:
    """Return the indices of the exterior facets of ``mesh`` owned by this rank."""
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    owned = mesh.topology.index_map(tdim - 1).size_local
    return np.asarray(facets[facets < owned], dtype=np.int32)


@dataclass(frozen=True)
class BoundaryTriangles:
    """Exterior facets of a tetrahedral body as triangles of their corners.

    Attributes:
        facets: The facets (mesh facet indices, owned by this rank).
        dofs: ``(m, 3)`` block index of each corner's displacement in ``V`` (a tetrahedron's
            first four nodes are its vertices, in the geometry and in a P1 or P2 ``V``).
        rest: ``(m, 3, 3)`` corner rest positions [m].

    """

    facets: np.ndarray
    dofs: np.ndarray
    rest: np.ndarray

    @classmethod
    def of(cls, mesh: Any, V: Any, facets: np.ndarray) -> BoundaryTriangles:
        """Return the triangles of ``facets`` (exterior, owned) of ``mesh`` with ``V``'s dofs."""
        tdim = mesh.topology.dim
        nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, facets)[:, :3]
        node_dof = np.zeros(mesh.geometry.x.shape[0], dtype=np.int64)
        node_dof[mesh.geometry.dofmaps[0][:, :4].reshape(-1)] = V.dofmap.list[:, :4].reshape(-1)
        return cls(np.asarray(facets), node_dof[nodes], mesh.geometry.x[nodes])

    def deformed(self, u: np.ndarray) -> np.ndarray:
        """Return the corners ``X + u`` (m, 3, 3) [m] of the displacement dof array ``u``."""
        return np.asarray(self.rest + np.asarray(u).reshape(-1, 3)[self.dofs])


def _cell_sizes(mesh: Any) -> np.ndarray:
    """Diameters of this rank's owned cells of ``mesh`` [m]."""
    tdim = mesh.topology.dim
    cells = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
    return np.asarray(mesh.h(tdim, cells)) if cells.size else np.zeros(0)


def min_cell_size(mesh: Any) -> float:
    """Smallest cell diameter of ``mesh`` over all ranks [m]."""
    sizes = _cell_sizes(mesh)
    local = float(sizes.min()) if sizes.size else math.inf
    return float(mesh.comm.allreduce(local, op=MPI.MIN))


def mean_cell_size(mesh: Any) -> float:
    """Mean cell diameter of ``mesh`` over all ranks [m]."""
    sizes = _cell_sizes(mesh)
    total = mesh.comm.allreduce(float(sizes.sum()), op=MPI.SUM)
    return float(total / max(mesh.comm.allreduce(int(sizes.size), op=MPI.SUM), 1))


class PenaltyContact:
    """One obstacle's penalty energy and reaction force as UFL forms of the displacement.

    The penalty is integrated over the exterior-facet subdomain ``facet_id`` of ``facets``
    (the same list for every obstacle of a body, as UFL requires of one form): all exterior
    facets in the forms compiled from the UFL, a subset in a solve that restricts them
    (:func:`models.backend.with_facet_domains`; the facets left out must have ``g >= 0``
    at every quadrature point, where the integrand is exactly zero).

    Args:
        options: The obstacle.
        mesh: The body's mesh.
        stiffness: Penalty stiffness k [Pa/m] (:func:`penalty_stiffness`).
        facet_id: The ``ds`` subdomain id of this obstacle's penalty (>= 0).
        facets: ``[(id, entities), ...]``: every obstacle's id with all exterior facets of the
            rank (:func:`models.backend.exterior_facet_domain`); None: this obstacle alone.

    """

    def __init__(self, options: ContactOptions, mesh: Any, stiffness: float, facet_id: int = 0,
                 facets: list[tuple[int, Any]] | None = None) -> None:
        self.options = options
        self.stiffness = dolfinx.fem.Constant(mesh, float(stiffness))
        self.point = dolfinx.fem.Constant(mesh, np.array(options.point))
        self.normal = dolfinx.fem.Constant(mesh, np.array(options.normal))
        self.center = dolfinx.fem.Constant(mesh, np.array(options.point))
        self.radius = dolfinx.fem.Constant(mesh, float(options.radius))
        self.facet_id = int(facet_id)
        if facets is None:
            facets = [(self.facet_id, exterior_facet_domain(mesh, exterior_facets(mesh)))]
        self.ds = ufl.Measure("ds", domain=mesh, subdomain_data=facets,
                              subdomain_id=self.facet_id,
                              metadata={"quadrature_degree": options.quadrature_degree})
        self._X = ufl.SpatialCoordinate(mesh)

    def gap_lower_bounds(self, points: np.ndarray) -> np.ndarray:
        """Return a lower bound of the gap ``g`` over each facet from its corners [m].

        Args:
            points: ``(facets, corners, 3)`` current positions ``X + u`` of facet corners.

        Returns:
            ``(facets,)``: the gap's minimum over the flat triangle of the corners, exact
            for P1 (the plane's gap is linear on it: its smallest corner gap; the sphere's
            is the distance from the centre to the triangle minus the radius). A curved (P2)
            facet may go lower.

        """
        p = np.asarray(points, dtype=np.float64)
        if self.options.obstacle == "plane":
            gaps = (p - np.asarray(self.point.value)) @ np.asarray(self.normal.value)
            return np.asarray(gaps.min(axis=1))
        return np.asarray(point_triangle_distance(np.asarray(self.center.value), p)
                          - float(self.radius.value))

    def set_center(self, center: Any) -> None:
        """Move the sphere's centre [m] (takes effect at the next solve)."""
        self.center.value[:] = vector3("contact.center", center)

    def gap(self, u: Any) -> tuple[Any, Any]:
        """Signed gap ``g`` and its gradient ``grad g`` at ``x = X + u`` (UFL)."""
        x = self._X + u
        if self.options.obstacle == "plane":
            return ufl.dot(x - self.point, self.normal), self.normal
        d = x - self.center
        dist = ufl.sqrt(ufl.dot(d, d))
        return dist - self.radius, d / dist

    def energy(self, u: Any) -> Any:
        """Penalty energy form ``int k/2 <g>_-^2 dA`` [J]."""
        g, _ = self.gap(u)
        neg = ufl.conditional(ufl.lt(g, 0.0), g, 0.0)
        return 0.5 * self.stiffness * neg**2 * self.ds

    def force_forms(self, u: Any) -> list[Any]:
        """Components of the force on the body ``int -k <g>_- grad g dA`` [N] (UFL forms)."""
        g, grad_g = self.gap(u)
        neg = ufl.conditional(ufl.lt(g, 0.0), g, 0.0)
        traction = -self.stiffness * neg * grad_g
        return [traction[i] * self.ds for i in range(3)]

    def center_hessian(self, u: Any) -> Any:
        """``K = d^2 e / dx^2`` of the penalty density ``e = k/2 <g>_-^2`` [Pa/m] (UFL 3 x 3).

        With ``n = (x - c)/d``, ``d = |x - c|`` and ``g = d - r`` (sphere only):

            K = k [ H(-g) n n^T + <g>_- (I - n n^T) / d ],

        the first term the normal penalty stiffness, the second (<= 0) the rotation of the
        normal. The density depends on ``x - c`` only, so ``K`` is also ``d^2 e / dc^2`` and
        ``-d^2 e / dx dc``.
        """
        if self.options.obstacle != "sphere":
            raise InputError("contact: the centre stiffness is defined for a sphere obstacle only")
        g, n = self.gap(u)
        d = g + self.radius
        inside = ufl.conditional(ufl.lt(g, 0.0), 1.0, 0.0)
        neg = ufl.conditional(ufl.lt(g, 0.0), g, 0.0)
        return self.stiffness * (inside * ufl.outer(n, n)
                                 + neg / d * (ufl.Identity(3) - ufl.outer(n, n)))

    def center_stiffness_forms(self, u: Any) -> list[list[Any]]:
        """Forms of ``K_c = dR/dc`` [N/m], the change of the force on the body with the centre.

        ``dR_i/dc_j = int K_ij dA`` (:meth:`center_hessian`). The body is held fixed, so this
        is the contact stiffness seen by a rigid sphere against a rigid surface; the compliant
        body makes the true ``dR/dc`` smaller (:meth:`center_coupling_forms`).
        """
        K = self.center_hessian(u)
        return [[K[i, j] * self.ds for j in range(3)] for i in range(3)]

    def center_coupling_forms(self, u: Any, w: Any) -> list[Any]:
        """Linear forms ``G_j(w) = int (K e_j) . w dA`` [N/m] of the test function ``w``.

        ``G_j`` is minus the change of the body's residual ``dPi/du`` with the centre's
        component ``j`` (:meth:`center_hessian`), and ``dR_i/du = -G_i^T``. A body in
        equilibrium with Jacobian ``A`` then moves by ``du/dc_j = A^{-1} G_j``, and the
        force it feels changes by

            dR/dc = K_c - G^T A^{-1} G,

        the stiffness of the sphere against the compliant body (a Schur complement,
        ``0 <= dR/dc <= K_c`` for a positive definite ``A``).
        """
        K = self.center_hessian(u)
        return [ufl.dot(K[:, j], w) * self.ds for j in range(3)]


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance from point ``p`` (3,) to each triangle of ``tri`` (m, 3, 3) [m].

    Inside the prism over the triangle: distance to its plane; else the nearest of the three
    edges (segments).
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    height = np.einsum("ij,ij->i", p - a, n)
    q = p - height[:, None] * n
    inside = np.ones(len(tri), dtype=bool)
    for s, e in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(e - s, q - s), n) >= 0.0
    edges = np.min([segment_distance(p, s, e) for s, e in ((a, b), (b, c), (c, a))], axis=0)
    return np.where(inside, np.abs(height), edges)


def segment_distance(p: np.ndarray, s: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Distance from ``p`` (3,) to the segments ``s_i e_i`` ((m, 3) each) [m]."""
    d = e - s
    t = np.clip(np.einsum("ij,ij->i", p - s, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    return np.asarray(np.linalg.norm(p - (s + t[:, None] * d), axis=1))
