"""Robustness: J > 0 through strong compression, step halving, SolverError with state restored."""

from __future__ import annotations

import re

import numpy as np
import pytest

from meshes.errors import InputError, SolverError
from models.backend import MPI, dolfinx
from models.body import BodyOptions, PinSpec
from models.materials import Material
from solvers.body import Body
from solvers.body_newton import NewtonOptions

MAT = Material(model="neo_hookean", E=1.0e5, nu=0.3)


def compression_body(degree: int, dt: float, n: int = 3, newton: NewtonOptions | None = None,
                     speed: float = 1.0) -> Body:
    """Unit cube, bottom face clamped, top face clamped and pushed down at ``speed`` per t."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, n, n, n)
    pins = (PinSpec(point=(0, 0, 0), normal=(0, 0, 1)),
            PinSpec(point=(0, 0, 1), normal=(0, 0, 1),
                    velocity=(0.0, 0.0, -speed)))
    opts = BodyOptions(degree=degree, dynamics="static", dt=dt, gravity=(0, 0, 0), pins=pins)
    return Body(mesh, MAT, opts, newton or NewtonOptions(rtol=1e-10))


@pytest.mark.parametrize("degree", [1, 2])
def test_strong_compression_keeps_det_f_positive(degree):
    """Compress 80 % in 8 load steps; the result equals the 32-step path's to 1e-6."""
    coarse = compression_body(degree, dt=0.1, n=2 if degree == 2 else 3)
    reports = [coarse.step() for _ in range(8)]
    fine = compression_body(degree, dt=0.025, n=2 if degree == 2 else 3)
    for _ in range(32):
        fine.step()
    diff = np.linalg.norm(coarse.u.x.array - fine.u.x.array) / np.linalg.norm(fine.u.x.array)
    dets = [r.min_det_f for r in reports]
    print(f"P{degree}: t={coarse.t:.3f} min det F per step={np.round(dets, 4)} "
          f"its={[r.newton_iterations for r in reports]} halvings="
          f"{[r.halvings for r in reports]} backtracks={coarse._static_solver.backtracks} "
          f"|u_8 - u_32|/|u_32|={diff:.2e}")
    assert coarse.t == pytest.approx(0.8)
    assert all(r.converged for r in reports)
    assert min(dets) > 0.0 and dets[-1] < 0.3  # strongly compressed, yet admissible
    assert diff < 1e-6


def test_one_shot_compression_needs_the_step_control():
    """50 % in one load step: the guarded solver halves and still reaches the same state."""
    one = compression_body(1, dt=0.5)
    report = one.step()
    ref = compression_body(1, dt=0.05)
    for _ in range(10):
        ref.step()
    diff = np.linalg.norm(one.u.x.array - ref.u.x.array) / np.linalg.norm(ref.u.x.array)
    print(f"one step of 0.5: halvings={report.halvings} substeps={report.substeps} "
          f"its={report.newton_iterations} min det F={report.min_det_f:.4f} diff={diff:.2e}")
    assert report.halvings >= 1 and report.min_det_f > 0.0
    assert diff < 1e-6


def test_forced_failure_raises_after_stated_halvings_and_restores_state():
    """max_it = 1 and a 250 % compression in one step: 3 halvings, then SolverError."""
    good = compression_body(1, dt=0.1)
    good.step()
    failing = NewtonOptions(max_it=1, max_halvings=3, rtol=1e-12, atol=1e-14, stol=0.0)
    body = compression_body(1, dt=5.0, newton=failing, speed=0.5)
    body.u.x.array[:] = good.u.x.array  # a good, non-trivial state at t = 0.1
    body.t = good.t
    before = body.u.x.array.copy()
    with pytest.raises(SolverError) as info:
        body.step()
    message = str(info.value)
    print(message)
    assert re.search(r"after 3 halvings \(last sub-step 6.250e-01", message)  # 5 / 2^3
    assert "min det F" in message and "SNES reason=-5" in message
    assert body.t == pytest.approx(0.1)
    assert np.array_equal(body.u.x.array, before)
    assert body.min_det_f() == pytest.approx(good.min_det_f(), rel=1e-14)


def cantilever(line_search: bool) -> Body:
    """A soft 1 m x 0.1 m x 0.1 m beam clamped at x = 0; its own weight bends it ~90 deg."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 0.1, 0.1]], [10, 1, 1],
                                   dolfinx.mesh.CellType.tetrahedron)
    opts = BodyOptions(pins=(PinSpec(point=(0, 0, 0), normal=(1, 0, 0)),))
    newton = NewtonOptions(rtol=1e-10, line_search=line_search)
    return Body(mesh, Material(E=2.0e4, nu=0.3), opts, newton)


def test_energy_line_search_is_what_makes_one_big_load_step_converge():
    body = cantilever(line_search=True)
    report = body.solve_static()
    solver = body._static_solver
    tip = body.u.x.array.reshape(-1, 3)[:, 2].min()
    print(f"line search on: its={report.newton_iterations} backtracks={solver.backtracks} "
          f"reversed steps={solver.flips} min det F={report.min_det_f:.4f} tip w={tip:.4f}")
    assert report.converged and report.min_det_f > 0.0 and solver.backtracks > 0
    assert -1.5 < tip < -1.0  # hangs down, and stretches under its own weight
    with pytest.raises(SolverError, match="SNES reason=-4"):  # DIVERGED_FNORM_NAN
        cantilever(line_search=False).solve_static()


def test_newton_options_validation():
    with pytest.raises(InputError, match="max_it"):
        NewtonOptions(max_it=0)
    with pytest.raises(InputError, match="line_search_type"):
        NewtonOptions(line_search_type="cubic")
    with pytest.raises(InputError, match="pin.components"):
        PinSpec(components=(3,))
    with pytest.raises(InputError, match="body.dynamics"):
        BodyOptions(dynamics="rk4")
