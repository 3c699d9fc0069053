"""Shared shell test cases (imported by tests; not a test module)."""

from __future__ import annotations

import numpy as np

from models.embedding.clusters import ClusterOptions, build_clusters
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState
from models.shell.topology import ShellTopology


def compressed_plate(points: np.ndarray, faces: np.ndarray,
                     clusters: int) -> tuple[ShellEnergy, np.ndarray]:
    """Unit plate held by a low-rank penalty to its 7 %-compressed self, noisy start.

    k_L = 1e3, k_B = 0.1, k_P = 1e3; the start is the target plus 1e-4 normal noise (seed 1).
    """
    topo = ShellTopology.from_faces(faces, len(points))
    h = build_clusters(points, faces, ClusterOptions(count=clusters)).H
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, penalty_hessian="low_rank")
    energy = ShellEnergy(topo, RestState.from_positions(topo, points), params, H=h)
    y = points.copy()
    y[:, 0] = 0.5 + 0.93 * (points[:, 0] - 0.5)
    energy.set_target(y)
    x0 = y.copy()
    x0[:, 2] += 1e-4 * np.random.default_rng(1).standard_normal(len(y))
    return energy, x0
