"""Wrinkling test problems for the decomposition tests and benchmark.

A square plate ``[0, L]^2`` held by the cluster penalty to a target compressed in x by the
fraction ``compression`` (``y_x = L/2 + (1 - compression)(X_x - L/2)``), as in
``tests/test_solvers/test_shell_newton_wrinkles.py``; the start is the target with a small seeded z
perturbation (``1e-4 L``) so the compressed plate can buckle out of plane.

:func:`plate_frame` turns it into the realistic per-frame problem of a frame loop (MISSION.md
section 1): the previous frame's minimiser (wrinkled) is moved by a new embedding target (a
compression increment) and is the warm start of the new frame's solve.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from meshes.errors import InputError
from meshes.shells import grid_plate
from models.embedding.clusters import ClusterOptions, build_clusters
from models.shell.energy import ShellParams
from models.shell.rest import RestState
from models.shell.topology import ShellTopology
from solvers.decomposition.patch_energy import ShellProblem


@dataclass(frozen=True)
class PlateCase:
    """A compressed plate problem.

    Attributes:
        cells: Grid cells per side ((cells + 1)^2 vertices).
        width: Side length L.
        compression: In-plane compression of the target along x (fraction, in [0, 1)).
        vertices_per_cluster: Cluster count = n / this (at least 4).
        params: Shell stiffnesses (the penalty Hessian must be "assembled").
        seed: Seed of the start perturbation.

    """

    cells: int = 20
    width: float = 1.0
    compression: float = 0.005
    vertices_per_cluster: int = 25
    params: ShellParams = field(default_factory=ShellParams)
    seed: int = 1

    def __post_init__(self) -> None:
        if self.cells < 2:
            raise InputError(f"PlateCase.cells: must be >= 2, got {self.cells}")
        if not 0 <= self.compression < 1:
            raise InputError(f"PlateCase.compression: must be in [0, 1), got "
                             f"{self.compression}")
        if self.vertices_per_cluster < 1:
            raise InputError("PlateCase.vertices_per_cluster: must be >= 1")


def compressed_target(points: np.ndarray, case: PlateCase) -> np.ndarray:
    """Target ``y_x = L/2 + (1 - compression)(X_x - L/2)`` (other coordinates unchanged)."""
    y = np.array(points, dtype=np.float64, copy=True)
    y[:, 0] = 0.5 * case.width + (1.0 - case.compression) * (y[:, 0] - 0.5 * case.width)
    return y


def plate_problem(case: PlateCase) -> tuple[ShellProblem, np.ndarray, np.ndarray]:
    """Build ``(problem, partition, x0)`` for a compressed plate."""
    pts, faces = grid_plate(case.cells, case.cells, case.width, case.width)
    topo = ShellTopology.from_faces(faces, len(pts))
    count = max(4, len(pts) // case.vertices_per_cluster)
    clusters = build_clusters(pts, faces, ClusterOptions(count=count))
    y = compressed_target(pts, case)
    problem = ShellProblem(topology=topo, rest=RestState.from_positions(topo, pts),
                           params=case.params, H=clusters.H.tocsr(), target=y)
    x0 = y.copy()
    x0[:, 2] += 1e-4 * case.width * np.random.default_rng(case.seed).standard_normal(len(y))
    return problem, clusters.partition, x0


Prepare = Callable[[ShellProblem, np.ndarray, np.ndarray], np.ndarray]
"""Minimiser of ``(problem, partition, x0)`` (the solver that prepares the previous frame)."""


@dataclass(frozen=True)
class FrameCase:
    """A warm-started frame: the wrinkled minimiser at ``plate.compression``, new target.

    Attributes:
        plate: The previous frame's plate (its compression wrinkles it).
        increment: Compression added by the new frame's target (fraction of the width).
        coarse_levels: Grid-sequencing levels of the preparation (each halves the cells; the
            coarse minimiser, interpolated, starts the finer solve); 0 = solve directly.

    """

    plate: PlateCase = field(default_factory=PlateCase)
    increment: float = 0.005
    coarse_levels: int = 1

    def __post_init__(self) -> None:
        if not 0 <= self.plate.compression + self.increment < 1:
            raise InputError(f"FrameCase.increment: compression + increment must be in [0, 1), "
                             f"got {self.plate.compression + self.increment}")
        if self.coarse_levels < 0:
            raise InputError(f"FrameCase.coarse_levels: must be >= 0, got {self.coarse_levels}")


def prolong(u: np.ndarray, cells: int, fine_cells: int) -> np.ndarray:
    """Bilinear interpolation of a grid-plate field (vertices ``(cells + 1)^2``) to a finer grid.

    ``grid_plate`` numbers vertex (i, j) (x index i, y index j) as ``j (cells + 1) + i``.
    """
    coarse = np.linspace(0.0, 1.0, cells + 1)
    interp = RegularGridInterpolator((coarse, coarse), u.reshape(cells + 1, cells + 1, -1))
    fine = np.linspace(0.0, 1.0, fine_cells + 1)
    yy, xx = np.meshgrid(fine, fine, indexing="ij")
    return interp(np.column_stack([yy.ravel(), xx.ravel()]))


def prepare_wrinkled(case: FrameCase, solve: Prepare) -> np.ndarray:
    """Minimiser of ``case.plate`` by grid sequencing (coarsest level from the noisy start)."""
    levels = [case.plate.cells]
    for _ in range(case.coarse_levels):
        if levels[-1] // 2 < 8:
            break
        levels.append(levels[-1] // 2)
    displacement, previous = None, 0
    for cells in reversed(levels):
        problem, partition, x0 = plate_problem(replace(case.plate, cells=cells))
        if displacement is not None:
            x0 = problem.target + prolong(displacement, previous, cells)
        x = solve(problem, partition, x0)
        displacement, previous = x - problem.target, cells
    return x


def plate_frame(case: FrameCase, x_prev: np.ndarray,
                ) -> tuple[ShellProblem, np.ndarray, np.ndarray]:
    """Build the new frame ``(problem, partition, x_start)``.

    ``x_start = x_prev + (y_new - y_prev)``: the previous minimiser moved with the embedding
    target (compression increased by ``case.increment``).
    """
    nxt = replace(case.plate, compression=case.plate.compression + case.increment)
    problem, partition, _ = plate_problem(nxt)
    before = compressed_target(problem.rest.positions, case.plate)
    return problem, partition, x_prev + (problem.target - before)
