"""Run small body problems and save the displacement gathered on rank 0 sorted by coordinates.

Usage: ``mpiexec -n N python tests/body_mpi_case.py OUT.npz`` (used by test_body_mpi.py).
"""

from __future__ import annotations

import sys

import numpy as np

from models.backend import MPI, dolfinx, mesh_from_arrays
from models.body import BodyOptions, PinSpec
from models.contact import ContactOptions
from models.materials import Material
from solvers.body import Body
from solvers.body_newton import NewtonOptions


def gathered(body: Body) -> np.ndarray:
    """Rows (X, Y, Z, ux, uy, uz) of all owned nodes on rank 0, sorted by (X, Y, Z)."""
    n_owned = body.V.dofmap.index_map.size_local
    X = body.V.tabulate_dof_coordinates()[:n_owned]
    U = body.u.x.array[: 3 * n_owned].reshape(-1, 3)
    rows = body.mesh.comm.gather(np.hstack([X, U]), root=0)
    if body.mesh.comm.rank != 0:
        return np.empty((0, 6))
    table = np.vstack(rows)
    keys = np.round(table[:, :3], 10)
    return table[np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))]


def compression_p2() -> Body:
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    pins = (PinSpec(point=(0, 0, 0), normal=(0, 0, 1)),
            PinSpec(point=(0, 0, 1), normal=(0, 0, 1), velocity=(0.1, 0, -1)))
    body = Body(mesh, Material(E=1e5, nu=0.3), BodyOptions(degree=2, dt=0.1, gravity=(0, 0, 0),
                                                            pins=pins))
    for _ in range(3):
        body.step()
    return body


def drop_p1(method: str = "auto") -> Body:
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0.002], [0.5, 0.4, 0.3]], [4, 3, 2],
                                   dolfinx.mesh.CellType.tetrahedron)
    opts = BodyOptions(dynamics="implicit_euler", dt=0.01, contacts=(ContactOptions(),))
    body = Body(mesh, Material(E=1e5, nu=0.3), opts, NewtonOptions(method=method))
    body.v.interpolate(lambda x: np.vstack([0.2 * x[1], 0 * x[0], -0.5 + 0 * x[0]]))
    for _ in range(5):
        body.step()
    return body


def cantilever_from_arrays() -> Body:
    """Rank 0 holds the arrays of a P1 box mesh; mesh_from_arrays distributes it."""
    comm = MPI.COMM_WORLD
    points, tets = np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64)
    if comm.rank == 0:
        serial = dolfinx.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 0.2, 0.2]], [6, 2, 2],
                                         dolfinx.mesh.CellType.tetrahedron)
        points, tets = serial.geometry.x, serial.geometry.dofmaps[0].astype(np.int64)
    mesh = mesh_from_arrays(comm, points, tets)
    pins = (PinSpec(point=(0, 0, 0), normal=(1, 0, 0)),)
    body = Body(mesh, Material(model="stvk", E=1e6, nu=0.3),
                BodyOptions(degree=2, pins=pins))
    body.solve_static()
    return body


def main(out: str) -> None:
    results = {}
    cases = (("compression_p2", compression_p2), ("drop_p1", drop_p1),
             ("drop_p1_iterative", lambda: drop_p1("iterative")),
             ("cantilever_from_arrays", cantilever_from_arrays))
    for name, build in cases:
        body = build()
        energies = body.energies()
        results[f"{name}_table"] = gathered(body)
        results[f"{name}_energies"] = np.array([energies[k] for k in sorted(energies)])
        results[f"{name}_reaction"] = (body.reaction_force() if body.contacts
                                       else np.zeros(3))
    if MPI.COMM_WORLD.rank == 0:
        np.savez(out, **results)
        print(f"ranks={MPI.COMM_WORLD.size} saved {out}")


if __name__ == "__main__":
    main(sys.argv[1])
