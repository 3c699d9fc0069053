"""A solver failure keeps the completed frames, records a diagnostic and exits 2 (1 and 2 ranks).

The failure is forced: one Newton iteration per step and no step halving, on the drop
scene of ``test_resume_kill`` (a block dropped on the ground) - frames 1 to 5 are free fall
(one Newton iteration is exact for the linear free-fall step), the contact step of frame 6
needs more and fails. The
diagnostic is cross-checked against the last completed frame's record: the body is restored
to the state at the end of frame 5, so its worst det F and energies must be those of that
record, and the worst cell is cross-checked against ``wrinkles.output.worst_cell`` on a field
with a known det F.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from support import drop_scene, wrinkles

from wrinkles.output import complete_steps

FORCE = ["--frames", "8", "--set", "newton.options.max_it=1",
         "--set", "newton.options.max_halvings=0"]


def check_failed_run(out: Path, stderr: str, returncode: int) -> dict:
    """Exit 2, one line naming the failure and its diagnostic, frames 1-5 kept; return it."""
    assert returncode == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    assert lines[0].startswith("error: body step failed at t=0.05")
    for part in ("diagnostic:", "smallest det F=", "in cell", "dominant energy term",
                 "E=50000.0", "nu=0.35", "dt=0.01", "newton_max_it=1"):
        assert part in lines[0], (part, lines[0])
    summary = json.loads((out / "summary.json").read_text())
    run = summary["run"]
    assert run["status"] == "failed" and run["failed_frame"] == 6
    assert [r["frame"] for r in summary["frames"]] == [1, 2, 3, 4, 5]
    assert complete_steps(out / "body.xdmf") == pytest.approx([0.0, 0.01, 0.02, 0.03, 0.04,
                                                               0.05], abs=1e-14)
    with h5py.File(out / "checkpoint.h5", "r") as h5:
        assert int(h5.attrs["frame"]) == 5
    diagnostic = run["diagnostic"]
    last = summary["frames"][-1]
    assert diagnostic["time"] == pytest.approx(last["time"], abs=1e-14)
    assert diagnostic["worst_det_f"]["min_det_f"] == pytest.approx(last["min_det_f"], rel=1e-12)
    assert diagnostic["energies"]["total"] == pytest.approx(last["energy"], rel=1e-12)
    assert diagnostic["dominant_energy"] in ("kinetic", "gravity")  # falling block
    assert diagnostic["parameters"]["newton_max_it"] == 1
    print(json.dumps(diagnostic, indent=1))
    return diagnostic


def test_forced_divergence_exits_2_with_diagnostic(tmp_path):
    out = tmp_path / "out"
    proc = wrinkles("run", str(drop_scene(tmp_path)), "--out", str(out), *FORCE)
    check_failed_run(out, proc.stderr, proc.returncode)


@pytest.mark.mpi
def test_forced_divergence_on_two_ranks_same_diagnostic(tmp_path, mpiexec):
    serial, parallel = tmp_path / "serial", tmp_path / "parallel"
    scene = str(drop_scene(tmp_path))
    proc = wrinkles("run", scene, "--out", str(serial), *FORCE)
    one = check_failed_run(serial, proc.stderr, proc.returncode)
    proc = mpiexec(["-m", "wrinkles", "run", scene, "--out", str(parallel), *FORCE],
                   n=2, timeout=180)
    two = check_failed_run(parallel, proc.stderr, proc.returncode)
    assert two["worst_det_f"]["min_det_f"] == pytest.approx(one["worst_det_f"]["min_det_f"],
                                                            rel=1e-9)
    # in free fall det F = 1 + O(1e-6) everywhere: the argmin cell is a near tie and may
    # differ between partitions; it must be a real cell of the mesh
    cells = json.loads((parallel / "summary.json").read_text())["run"]["mesh"]["cells"]
    assert 0 <= two["worst_det_f"]["cell"] < cells
    assert all(0.0 <= c <= 0.4 for c in two["worst_det_f"]["cell_centroid"][:2])


def test_worst_cell_locates_the_known_minimum():
    """``u = (0, 0, c z^2 / 2)`` has ``det F = 1 + c z``: smallest at the top, c < 0."""
    from meshes.structured import structured_box
    from models.backend import MPI, mesh_from_arrays
    from models.body import BodyOptions
    from models.materials import Material
    from solvers.body import Body
    from wrinkles.output import worst_cell

    tet = structured_box((3, 3, 3))
    mesh = mesh_from_arrays(MPI.COMM_WORLD, tet.points, tet.tets)
    body = Body(mesh, Material(E=1e4, nu=0.3), BodyOptions(degree=2))
    c = -0.6
    body.u.interpolate(lambda x: np.vstack([0 * x[0], 0 * x[0], 0.5 * c * x[2] ** 2]))
    worst = worst_cell(body)
    assert worst["min_det_f"] == pytest.approx(body.min_det_f(), rel=1e-14)
    top = 1.0 - 1.0 / 3.0
    assert 1.0 + c - 1e-12 < worst["min_det_f"] < 1.0 + c * top  # a point of the top layer
    assert worst["cell_centroid"][2] > top
    assert worst["min_det_f"] == pytest.approx(1.0 + c * worst_z(body), rel=1e-12)


def worst_z(body) -> float:
    """Largest z of the volume quadrature points (where det F = 1 + c z is smallest)."""
    from models.backend import basix

    points, _ = basix.make_quadrature(body.mesh.basix_cell(), body.options.qdegree)
    geo = body.mesh.geometry
    corners = geo.x[geo.dofmaps[0]]  # (cells, 4, 3)
    bary = np.column_stack([1 - points.sum(axis=1), points])
    return float(np.einsum("qk,ckd->cqd", bary, corners)[..., 2].max())


def test_stagnation_names_a_hinge_folded_flat() -> None:
    """Two triangles folded back to back (bend angle pi, where the hinge energy jumps) are
    named by the stagnation diagnostic; a flat hinge and a 90-degree fold are not."""
    from types import SimpleNamespace

    from models.shell.topology import ShellTopology
    from solvers.shell_newton import folded_hinge, worst_stencil

    faces = np.array([[0, 1, 2], [1, 0, 3]])
    energy = SimpleNamespace(topology=ShellTopology.from_faces(faces, 4))
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0]])
    bent = flat.copy()
    bent[3] = [0.5, 0.0, 1.0]
    folded = flat.copy()
    folded[3] = [0.5, 1.0, 0.0]  # on top of vertex 2: the faces lie back to back
    assert folded_hinge(energy, flat) == "" and folded_hinge(energy, bent) == ""
    message = worst_stencil(energy, np.ones(12), folded)
    print(message)
    assert "hinge 0 [0, 1, 2, 3] is folded flat" in message and "3.141593" in message
