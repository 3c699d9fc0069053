"""Decomposed (block) solve on one worker against the monolithic Newton solve."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import SolverError
from solvers.decomposition.block import BlockOptions, patch_colours, serial_block_solve
from solvers.decomposition.demo import PlateCase, plate_problem
from solvers.decomposition.patch_energy import PatchEnergy
from solvers.decomposition.patches import build_patches
from solvers.shell_newton import ShellNewtonOptions, minimize

WRINKLED = PlateCase(cells=12, compression=0.07)  # 169 vertices, 6 clusters, buckles
MILD = PlateCase(cells=12, compression=0.005)


def _setup(case: PlateCase, n_parts: int):
    problem, partition, x0 = plate_problem(case)
    energy = problem.energy()
    g0 = float(np.linalg.norm(energy.evaluate(x0, order=1).grad))
    x_ref, ref = minimize(energy, x0, ShellNewtonOptions(rtol=1e-8, gradient_scale=g0))
    patches = build_patches(problem.topology, partition, n_parts)
    energies = [PatchEnergy(problem, p.interior) for p in patches.patches]
    return energy, energies, x0, g0, x_ref, ref


@pytest.mark.parametrize(("case", "method"), [(WRINKLED, "gauss_seidel"), (WRINKLED, "jacobi"),
                                              (MILD, "jacobi")])
def test_block_solve_matches_monolithic(case: PlateCase, method: str) -> None:
    energy, energies, x0, g0, x_ref, ref = _setup(case, 4)
    # block Jacobi converges linearly and slowly (about 500 outer iterations on the wrinkled
    # plate, a few more or less with the machine's rounding): the budget is not under test
    x, rep = serial_block_solve(energies, x0, BlockOptions(method=method, rtol=1e-8,
                                                           gradient_scale=g0, max_outer=1000))
    w = energy.value(x)
    gap, diff = abs(w - ref.energy) / abs(ref.energy), np.abs(x - x_ref).max() / case.width
    g_final = np.linalg.norm(energy.evaluate(x, order=1).grad)
    print(f"{method} compression={case.compression}: outer={rep.outer_iterations} "
          f"inner={rep.inner_iterations} colours={rep.colours} rejected={rep.rejected_mixing} "
          f"|g|={g_final:.2e} (tol {rep.tolerance:.2e}) energy gap {gap:.2e} max diff {diff:.2e} "
          f"amplitude {np.abs(x_ref[:, 2]).max():.3f}; monolithic it={ref.iterations}")
    assert rep.converged
    assert g_final <= rep.tolerance * (1 + 1e-6)  # the report's norm is the true one
    assert gap < 1e-8
    assert diff < 1e-6


def test_wrinkled_case_buckles() -> None:
    """The test problem is a real wrinkling problem (out-of-plane amplitude >> start noise)."""
    *_, x_ref, ref = _setup(WRINKLED, 2)
    assert ref.converged
    assert np.abs(x_ref[:, 2]).max() > 100 * 1e-4 * WRINKLED.width


def test_colouring_separates_dependent_patches() -> None:
    problem, partition, _ = plate_problem(PlateCase(cells=30))  # 961 vertices, 38 clusters
    patches = build_patches(problem.topology, partition, 8)
    energies = [PatchEnergy(problem, p.interior) for p in patches.patches]
    colours = patch_colours([e.interior for e in energies], [e.halo for e in energies], 961)
    for p, ep in enumerate(energies):
        for q, eq in enumerate(energies):
            if p != q and colours[p] == colours[q]:
                assert not np.intersect1d(ep.halo, eq.interior).size
    print(f"8 patches -> {colours.max() + 1} colours")
    assert colours.max() + 1 < len(energies)


def test_failing_patch_raises() -> None:
    _, energies, x0, *_ = _setup(MILD, 4)
    with pytest.raises(SolverError, match="patch 2: SolverError: forced failure"):
        serial_block_solve(energies, x0, BlockOptions(fail_patch=2))
