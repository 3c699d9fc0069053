"""Cross-check TetMesh against dolfinx: same volume and same boundary, serial and 2 ranks."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest

SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np
    from models.backend import MPI, dolfinx, ufl, mesh_from_arrays
    from meshes import sofa, sphere

    comm = MPI.COMM_WORLD
    out = {}
    for name, build in (("sphere", lambda: sphere(1.0, 0.3)), ("sofa", lambda: sofa(h=0.2))):
        m = comm.bcast(build() if comm.rank == 0 else None, root=0)
        empty = comm.rank != 0
        mesh = mesh_from_arrays(comm, m.points[:0] if empty else m.points,
                                m.tets[:0] if empty else m.tets)
        form = dolfinx.fem.form(1.0 * ufl.dx(domain=mesh))
        volume = comm.allreduce(dolfinx.fem.assemble_scalar(form), op=MPI.SUM)
        area_form = dolfinx.fem.form(1.0 * ufl.ds(domain=mesh))
        area = comm.allreduce(dolfinx.fem.assemble_scalar(area_form), op=MPI.SUM)
        mesh.topology.create_connectivity(2, 3)
        facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
        owned = int((facets < mesh.topology.index_map(2).size_local).sum())
        p = m.points[m.boundary]
        ours_area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]),
                                         axis=1).sum()
        out[name] = dict(volume=volume, ours=m.volume, area=area, ours_area=ours_area,
                         facets=comm.allreduce(owned, op=MPI.SUM), boundary=len(m.boundary))
    if comm.rank == 0:
        print(json.dumps(out))
""")


def check(result: dict[str, dict[str, float]]) -> None:
    for name, r in result.items():
        assert abs(r["volume"] - r["ours"]) <= 1e-12 * r["ours"], name
        assert abs(r["area"] - r["ours_area"]) <= 1e-12 * r["ours_area"], name
        assert r["facets"] == r["boundary"], name


@pytest.fixture
def script(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("WRINKLES_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "dolfinx_check.py"
    path.write_text(SCRIPT)
    return path


def test_dolfinx_agrees_serial(mpiexec, script: Path) -> None:
    proc = mpiexec([str(script)], n=1, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    print(result)
    check(result)


@pytest.mark.mpi
def test_dolfinx_agrees_on_two_ranks(mpiexec, script: Path) -> None:
    proc = mpiexec([str(script)], n=2, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    print(result)
    check(result)
