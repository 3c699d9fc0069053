"""The extreme cases of the body and the shell (built by tests/wrinkles/test_extremes.py and run
on N ranks by tests/extremes_mpi_case.py)."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from meshes.structured import structured_box
from meshes.validate import validate
from models.backend import MPI, mesh_from_arrays
from models.body import BodyOptions, PinSpec
from models.contact import ContactOptions
from models.embedding.clusters import ClusterOptions, build_clusters
from models.embedding.subdivision import SubdivisionOptions, subdivide
from models.embedding.surface import boundary_surface
from models.materials import Material
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import MIN_QUALITY, RestState
from models.shell.topology import ShellTopology
from solvers.body import Body
from solvers.body_newton import NewtonOptions

L = 0.1
"""Edge of the body cube [m]."""


MAX_IT = 30
"""Newton iterations allowed per body solve (the SNES cap)."""


def cube_mesh(points: np.ndarray | None = None) -> Any:
    """The 3x3x3 structured cube of edge ``L`` (optionally with moved points)."""
    tet = structured_box((3, 3, 3), (L, L, L))
    pts = tet.points if points is None else points
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        clean = validate(pts, tet.tets, source="extreme cube")
    return distributed(clean.points, clean.tets)


def distributed(points: np.ndarray, tets: np.ndarray) -> Any:
    """The mesh on COMM_WORLD: rank 0 passes the arrays, the others empty ones (as
    ``mesh_from_arrays`` requires; passing them on every rank duplicates cells and crashed
    the 2-rank run with heap corruption)."""
    root = MPI.COMM_WORLD.rank == 0
    return mesh_from_arrays(MPI.COMM_WORLD, points if root else np.zeros((0, 3)),
                            tets if root else np.zeros((0, 4), dtype=np.int64))


def press_pins(top_velocity: float) -> tuple[PinSpec, ...]:
    """Bottom face clamped; top face clamped to ``u_z = top_velocity * t``."""
    return (PinSpec(point=(0.0, 0.0, 0.0), tol=1e-9),
            PinSpec(point=(0.0, 0.0, L), tol=1e-9,
                    velocity=(0.0, 0.0, top_velocity)))


class EnergyLog:
    """Energy after every Newton iteration of a body solver (SNES monitor)."""

    def __init__(self, body: Body) -> None:
        self.body, self.sequences = body, []
        self.scale = (body.material.mu + body.material.lmbda) * L**3
        for solver in (body._static_solver, body._dynamic_solver):  # test-only access
            if solver is not None:
                solver.problem.solver.setMonitor(self._monitor(solver))

    def _monitor(self, solver: Any) -> Callable[..., None]:
        def monitor(snes: Any, it: int, _fnorm: float) -> None:
            if it == 0:
                self.sequences.append([])
            self.sequences[-1].append(solver._objective(snes, snes.getSolution()))
        return monitor

    def worst_increase(self) -> float:
        """Largest ``Pi_{k+1} - Pi_k`` relative to ``|Pi_k| + scale`` over all solves."""
        worst = -math.inf
        for seq in self.sequences:
            e = np.asarray(seq)
            if e.size > 1:
                worst = max(worst, float(np.max(np.diff(e) / (np.abs(e[:-1]) + self.scale))))
        return worst


def run_body(body: Body, steps: int, before: Callable[[int], None] | None = None
             ) -> dict[str, Any]:
    """Take ``steps`` body steps; return the record (iterations, fallbacks, det F)."""
    log = EnergyLog(body)
    reports = []
    for k in range(steps):
        if before is not None:
            before(k)
        reports.append(body.step())
    solvers = [s for s in (body._static_solver, body._dynamic_solver) if s is not None]
    its = [r.newton_iterations for r in reports]
    return {"outcome": "converged", "steps": steps, "iterations": sum(its),
            "max_iterations": max(max(len(s) - 1 for s in log.sequences), 0),
            "iterations_per_step": its, "halvings": sum(r.halvings for r in reports),
            "backtracks": sum(s.backtracks for s in solvers),
            "flips": sum(s.flips for s in solvers),
            "min_det_f": min(r.min_det_f for r in reports),
            "energy": reports[-1].energy, "worst_energy_increase": log.worst_increase()}


def body(material: Material, options: BodyOptions, mesh: Any = None,
         newton: NewtonOptions | None = None) -> Body:
    return Body(mesh if mesh is not None else cube_mesh(), material, options,
                newton or NewtonOptions(max_it=MAX_IT))


BodyCase = tuple[Body, int, Callable[[int], None] | None]
"""A body case: the body, its number of steps and an optional per-step hook."""


def nu_case(nu: float) -> BodyCase:
    """30 % static compression in 3 load steps of a cube with Poisson ratio ``nu``."""
    return body(Material(E=1e4, nu=nu), BodyOptions(dynamics="static", dt=1.0,
                                                    gravity=(0, 0, 0),
                                                    pins=press_pins(-0.1 * L))), 3, None


def compression_case(degree: int, steps: int, newton: NewtonOptions | None = None
                     ) -> BodyCase:
    """Compression to half height in ``steps`` static load steps (P``degree``)."""
    options = BodyOptions(degree=degree, dynamics="static", dt=1.0, gravity=(0, 0, 0),
                          pins=press_pins(-0.5 * L / steps))
    return body(Material(E=1e4, nu=0.3), options, newton=newton), steps, None


def time_step_case(dynamics: str, dt: float) -> BodyCase:
    """Block 1 cm above the ground, 3 dynamic steps of ``dt``."""
    ground = ContactOptions(obstacle="plane", point=(0.0, 0.0, -0.01), normal=(0.0, 0.0, 1.0))
    return body(Material(E=1e4, nu=0.3, density=1000.0),
                BodyOptions(dynamics=dynamics, dt=dt, contacts=(ground,))), 3, None


def sphere_case() -> BodyCase:
    """A clamped block indented by a sphere moving down at 10 m/s (20 steps of 0.1 ms)."""
    dt, speed, radius = 1e-4, 10.0, 0.04
    start = np.array([L / 2, L / 2, L + radius])
    sphere = ContactOptions(obstacle="sphere", point=tuple(start), radius=radius)
    b = body(Material(E=1e4, nu=0.3), BodyOptions(dynamics="implicit_euler", dt=dt,
                                                  contacts=(sphere,), gravity=(0, 0, 0),
                                                  pins=press_pins(0.0)[:1]))
    move = lambda k: b.set_sphere_center(start - [0.0, 0.0, speed * dt * (k + 1)])  # noqa: E731
    return b, 20, move


def coarse_surface() -> tuple[np.ndarray, np.ndarray]:
    """Boundary surface of a 2x2x1 box 0.2 x 0.2 x 0.1 m (coarse body surface)."""
    tet = structured_box((2, 2, 1), (0.2, 0.2, 0.1))
    surface = boundary_surface(tet.points, tet.tets)
    return surface.vertices, surface.faces


def shell_case(params: ShellParams, levels: int = 2, flatness: float | None = None,
               min_quality: float = MIN_QUALITY) -> tuple[ShellEnergy, np.ndarray]:
    """Shell on the subdivided surface, clusters pulling it to the surface compressed 15 %;
    with ``flatness`` one triangle of the rest state is squashed (:func:`squash_triangle`);
    ``min_quality`` is passed to :meth:`RestState.from_positions`."""
    v0, f0 = coarse_surface()
    sub = subdivide(v0, f0, SubdivisionOptions(levels=levels))
    x, faces = sub.vertices, sub.faces
    if flatness is not None:
        x = squash_triangle(x, faces, flatness)
    topo = ShellTopology.from_faces(faces, len(x))
    clusters = build_clusters(x, faces, ClusterOptions(count=min(12, len(x) // 2)))
    if levels >= 3:  # H^T H of 12 wide clusters is nearly dense at 10^3+ vertices
        params = dataclasses.replace(params, penalty_hessian="low_rank")
    energy = ShellEnergy(topo, RestState.from_positions(topo, x, min_quality), params, H=clusters.H)
    centre = x.mean(axis=0)
    target = centre + (x - centre) * np.array([0.85, 1.0, 1.0])
    energy.set_target(target)
    rng = np.random.default_rng(7)
    noise = 1e-4 if flatness is None else 1e-4 * flatness  # never invert the sliver
    return energy, target + noise * rng.standard_normal(target.shape)


def squash_triangle(x: np.ndarray, faces: np.ndarray, flatness: float) -> np.ndarray:
    """Move a vertex with a flat star toward the midpoint of the opposite edge of one of its
    triangles, leaving that triangle ``flatness`` of its area (a sliver; the rest of the star
    stays unfolded since the midpoint lies on the star's boundary)."""
    normals = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    for v in range(len(x)):
        star = np.flatnonzero((faces == v).any(axis=1))
        if len(star) >= 5 and np.allclose(normals[star], normals[star[0]], atol=1e-12):
            face = faces[star[0]]
            others = face[face != v]
            mid = 0.5 * (x[others[0]] + x[others[1]])
            out = x.copy()
            out[v] = mid + flatness * (x[v] - mid)
            return out
    raise AssertionError("no vertex with a flat star")


def ratio_params(ratio: float) -> ShellParams:
    """Skin/body stiffness ratio: ``k_L``, ``k_B`` scaled by ``ratio`` against ``k_P``."""
    return ShellParams(k_L=1e3 * ratio, k_B=1e-1 * ratio, k_P=1e3)
