"""Wrinkling test problems for the decomposition tests and benchmark.

A square plate ``[0, L]^2`` held by the cluster penalty to a target compressed in x by the
fraction ``compression`` (``y_x = L/2 + (1 - compression)(X_x - L/2)``), as in
``tests/test_shell_solver_wrinkles.py``; the start is the target with a small seeded z
perturbation (``1e-4 L``) so the compressed plate can buckle out of plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from meshes.shells import grid_plate
from models.embedding.clusters import ClusterOptions, build_clusters
from models.errors import InputError
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


def plate_problem(case: PlateCase) -> tuple[ShellProblem, np.ndarray, np.ndarray]:
    """Build ``(problem, partition, x0)`` for a compressed plate."""
    pts, faces = grid_plate(case.cells, case.cells, case.width, case.width)
    topo = ShellTopology.from_faces(faces, len(pts))
    count = max(4, len(pts) // case.vertices_per_cluster)
    clusters = build_clusters(pts, faces, ClusterOptions(count=count))
    y = pts.copy()
    y[:, 0] = 0.5 * case.width + (1.0 - case.compression) * (pts[:, 0] - 0.5 * case.width)
    problem = ShellProblem(topology=topo, rest=RestState.from_positions(topo, pts),
                           params=case.params, H=clusters.H.tocsr(), target=y)
    x0 = y.copy()
    x0[:, 2] += 1e-4 * case.width * np.random.default_rng(case.seed).standard_normal(len(y))
    return problem, clusters.partition, x0
