"""Surface, subdivision and B on 1 and 2 MPI ranks give the same shell and the same B f."""

from __future__ import annotations

import numpy as np
import pytest

SCRIPT = r"""
import sys
import numpy as np
from models.backend import MPI, dolfinx
from models.embedding.embedding import apply_to_function, add_transpose_to_function
from models.embedding.embedding import build_embedding, mesh_surface
from models.embedding.subdivision import SubdivisionOptions, subdivide

comm = MPI.COMM_WORLD
mesh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [1.0, 1.5, 1.2]], [3, 4, 3],
                               dolfinx.mesh.CellType.tetrahedron)
surf = mesh_surface(mesh)
sub = subdivide(surf.vertices, surf.faces, SubdivisionOptions(levels=2, scheme="loop"))
centre = np.array([0.5, 0.75, 0.6])
outside = centre + 1.01 * (sub.vertices - centre)  # off the surface: closest-cell fallback
out = {"vertices": surf.vertices, "faces": surf.faces, "node_map": surf.node_map,
       "shell": sub.vertices}

def field(x):
    return np.stack([np.sin(2 * x[0]) * np.cos(x[1]), np.exp(x[2]) - x[0], x[1] ** 3])

for degree in (1, 2):
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (3,)))
    u = dolfinx.fem.Function(V)
    u.interpolate(field)
    for name, pts in (("shell", sub.vertices), ("outside", outside)):
        emb = build_embedding(V, pts)
        key = f"p{degree}_{name}"
        out[key + "_Bf"] = apply_to_function(emb, u)
        out[key + "_rest"] = emb.apply(V.tabulate_dof_coordinates())
        out[key + "_report"] = np.array([emb.report.n_inside, emb.report.n_extrapolated,
                                         emb.report.max_distance])
        forces = np.cos(np.arange(pts.size)).reshape(-1, 3)
        f = dolfinx.fem.Function(V)
        add_transpose_to_function(emb, forces, f)
        n_owned = V.dofmap.index_map.size_local * 3
        dot = comm.allreduce(float(f.x.array[:n_owned] @ u.x.array[:n_owned]), op=MPI.SUM)
        out[key + "_adjoint"] = np.array([dot, float(np.sum(forces * out[key + "_Bf"]))])
if comm.rank == 0:
    np.savez(sys.argv[1], **out)
"""


def run(mpiexec, tmp_path, n):
    path = tmp_path / f"emb_{n}.npz"
    proc = mpiexec(["-c", SCRIPT, str(path)], n=n, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return dict(np.load(path))


@pytest.mark.mpi
def test_serial_and_two_ranks_identical(mpiexec, tmp_path):
    one, two = run(mpiexec, tmp_path, 1), run(mpiexec, tmp_path, 2)
    for key in ("vertices", "faces", "node_map", "shell"):
        np.testing.assert_array_equal(one[key], two[key], err_msg=key)
    for degree in (1, 2):
        for name in ("shell", "outside"):
            key = f"p{degree}_{name}"
            np.testing.assert_allclose(two[key + "_Bf"], one[key + "_Bf"], rtol=0, atol=1e-12)
            np.testing.assert_allclose(two[key + "_rest"], one[key + "_rest"], rtol=0,
                                       atol=1e-12)
            np.testing.assert_allclose(one[key + "_rest"],
                                       one["shell"] if name == "shell" else
                                       np.array([0.5, 0.75, 0.6]) + 1.01 * (
                                           one["shell"] - np.array([0.5, 0.75, 0.6])),
                                       rtol=0, atol=1e-12)
            np.testing.assert_array_equal(two[key + "_report"][:2], one[key + "_report"][:2])
            for res in (one, two):
                a, b = res[key + "_adjoint"]
                assert a == pytest.approx(b, rel=1e-12)
    assert one["p1_outside_report"][1] > 0  # the fallback was exercised
