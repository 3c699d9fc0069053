"""Multigrid on the subdivision hierarchy: prolongation, CG to true residual 1e-8, Newton."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import shellcases

from meshes.shells import grid_plate, icosphere
from models.errors import InputError
from models.shell.energy import ShellEnergy
from solvers.linear import AugmentedPenaltySolver
from solvers.multigrid import (
    MultigridLinearSystem,
    MultigridOptions,
    ShellHierarchy,
    eisenstat_walker,
)
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver, ShellSolveReport


def compressed_plate(hierarchy: ShellHierarchy, clusters: int) -> tuple[ShellEnergy, np.ndarray]:
    """Plate of the hierarchy, low-rank penalty to its 7 %-compressed self, noisy start."""
    return shellcases.compressed_plate(hierarchy.vertices, hierarchy.faces, clusters)


@pytest.mark.parametrize("scheme", ["linear", "loop"])
def test_prolongation_reproduces_linear_fields(scheme: str) -> None:
    pts, faces = icosphere(1)
    hier = ShellHierarchy.build(pts, faces, 3, scheme)
    rng = np.random.default_rng(3)
    m, c = rng.standard_normal((3, 3)), rng.standard_normal(3)
    coarse = pts @ m.T + c  # an affine vector field u(x) = M x + c on the coarse vertices
    fine_dofs = coarse.reshape(-1)
    for p in hier.prolongations():
        fine_dofs = p @ fine_dofs
    exact = hier.vertices @ m.T + c  # the same field at the fine vertices
    err = np.max(np.abs(fine_dofs.reshape(-1, 3) - exact))
    print(f"{scheme}: sizes {hier.level_sizes}, max |P u_c - u(x_f)| = {err:.2e}")
    assert hier.level_sizes == (42, 162, 642, 2562)
    assert err < 1e-13


def newton_operator(a: sp.csr_matrix, g: sp.csr_matrix) -> sla.LinearOperator:
    """``A + G^T G`` matrix-free (the assembled G^T G fills in)."""
    return sla.LinearOperator(a.shape, matvec=lambda v: a @ v + g.T @ (g @ v), dtype=np.float64)


def jacobi_cg_iterations(op: sla.LinearOperator, diag: np.ndarray, b: np.ndarray) -> int:
    """Iterations of Jacobi-preconditioned CG (scipy) to relative residual 1e-8."""
    count = [0]
    sla.cg(op, b, rtol=1e-8, atol=0.0, maxiter=20000, M=sp.diags(1.0 / diag),
           callback=lambda _: count.__setitem__(0, count[0] + 1))
    return count[0]


def test_cg_true_residual_and_level_growth() -> None:
    mg_its, jac_its, sizes = [], [], []
    for lev in (2, 3, 4):  # 625, 2401, 9409 vertices over the same 6x6 coarse plate
        hier = ShellHierarchy.build(*grid_plate(6, 6), levels=lev)
        energy, x0 = compressed_plate(hier, clusters=max(4, len(hier.vertices) // 75))
        ev = energy.evaluate(x0, hessian="gauss_newton")
        assert ev.grad is not None and ev.hess is not None and ev.penalty_factor is not None
        mg = MultigridLinearSystem(hier.prolongations(), MultigridOptions(rtol=1e-8))
        mg.factorize(ev, 0.0)
        dx = mg.solve(-ev.grad)
        g = ev.penalty_factor
        direct = AugmentedPenaltySolver(ev.hess, g)  # (A + G^T G) without assembling G^T G
        direct.factorize(ev.hess, g)
        dx_ref = direct.solve(-ev.grad)
        full = newton_operator(ev.hess, g)
        true = np.linalg.norm(full @ dx + ev.grad) / np.linalg.norm(ev.grad)
        gap = np.linalg.norm(dx - dx_ref) / np.linalg.norm(dx_ref)
        diag = ev.hess.diagonal() + np.asarray(g.multiply(g).sum(axis=0)).ravel()
        jac = jacobi_cg_iterations(full, diag, -ev.grad)
        print(f"n={len(hier.vertices)} levels {lev}: MG-CG {mg.stats.iterations[0]} its, true "
              f"residual {true:.2e} (reported {mg.stats.true_residuals[0]:.2e}), |dx - "
              f"dx_direct|/|dx_direct| {gap:.1e}; Jacobi-CG {jac} its")
        assert mg.stats.fallbacks == 0 and true <= 1e-8
        assert true == pytest.approx(mg.stats.true_residuals[0], rel=1e-6)
        assert gap < 1e-4
        mg_its.append(mg.stats.iterations[0])
        jac_its.append(jac)
        sizes.append(len(hier.vertices))
    mg_rate = np.polyfit(np.log(sizes), np.log(mg_its), 1)[0]
    jac_rate = np.polyfit(np.log(sizes), np.log(jac_its), 1)[0]
    print(f"iterations ~ n^p: multigrid p = {mg_rate:.3f}, Jacobi p = {jac_rate:.3f}")
    # measured: MG-CG 15 / 20 / 21 its (p = 0.12: +5, +1 per level), Jacobi-CG 471 / 883 /
    # 1284 its (p = 0.37)
    assert mg_rate < 0.25 and jac_rate > 2.5 * mg_rate
    assert max(mg_its) <= 40


@pytest.mark.parametrize("smoother_pc,cycle", [("sor", "v"), ("jacobi", "w")])
def test_smoother_and_cycle_variants(smoother_pc: str, cycle: str) -> None:
    hier = ShellHierarchy.build(*grid_plate(6, 6), levels=3)
    energy, x0 = compressed_plate(hier, clusters=32)
    ev = energy.evaluate(x0, hessian="gauss_newton")
    assert ev.grad is not None
    opts = MultigridOptions(rtol=1e-8, smoother_pc=smoother_pc, cycle=cycle)
    mg = MultigridLinearSystem(hier.prolongations(), opts)
    mg.factorize(ev, 0.0)
    dx = mg.solve(-ev.grad)
    true = mg.true_residual(dx, -ev.grad)
    print(f"{smoother_pc}/{cycle}: {mg.stats.iterations[0]} CG its, true residual {true:.2e}")
    assert mg.stats.fallbacks == 0 and true <= 1e-8 and mg.stats.iterations[0] <= 30


@pytest.fixture(scope="module")
def wrinkle() -> tuple[ShellHierarchy, ShellEnergy, np.ndarray]:
    hier = ShellHierarchy.build(*grid_plate(5, 5), levels=2)  # 21 x 21 vertices
    energy, x0 = compressed_plate(hier, clusters=20)
    return hier, energy, x0


def newton(wrinkle, **options: object) -> tuple[np.ndarray, ShellSolveReport]:
    """Mixed Gauss-Newton-then-exact Newton to rtol 1e-9 with the given options."""
    hier, energy, x0 = wrinkle
    opts = ShellNewtonOptions(rtol=1e-9, hessian="exact", far_hessian="gauss_newton",
                              **options)  # type: ignore[arg-type]
    return ShellNewtonSolver(energy, opts, hierarchy=hier).minimize(x0)


def distance(x: np.ndarray, ref: np.ndarray) -> float:
    """Max vertex distance to ``ref`` or its z-mirror (the same wrinkled minimum)."""
    mirror = ref * np.array([1.0, 1.0, -1.0])
    return float(min(np.max(np.abs(x - ref)), np.max(np.abs(x - mirror))))


def test_newton_multigrid_same_minimiser(wrinkle) -> None:
    x_direct, direct = newton(wrinkle)
    x_mg, mg = newton(wrinkle, linear_method="multigrid")
    x_ew, ew = newton(wrinkle, linear_method="multigrid",
                      multigrid=MultigridOptions(forcing="eisenstat_walker"))
    for name, r, x in (("direct", direct, x_direct), ("multigrid", mg, x_mg),
                       ("multigrid + EW", ew, x_ew)):
        print(f"{name}: {r.summary()}; distance {distance(x, x_direct):.1e}")
        assert r.converged
        assert abs(r.energy - direct.energy) <= 1e-12 * direct.energy
        assert distance(x, x_direct) < 1e-6
    assert np.max(np.abs(x_direct[:, 2])) > 0.01  # it wrinkles
    # a CG solve to 1e-8 is as good as the factorisation: same Newton iterations
    assert mg.iterations == direct.iterations
    # the exact phase is indefinite: CG breaks down and the direct solve takes over (and the
    # shift loop moves on); measured 30 fallbacks in 38 iterations
    assert mg.krylov_fallbacks > 0
    assert ew.krylov_iterations < 0.5 * mg.krylov_iterations  # inexact Newton: fewer CG its


def test_gauss_newton_phase_needs_no_fallback(wrinkle) -> None:
    hier, energy, x0 = wrinkle
    opts = ShellNewtonOptions(rtol=1e-3, hessian="gauss_newton", linear_method="multigrid")
    x, report = ShellNewtonSolver(energy, opts, hierarchy=hier).minimize(x0)
    print(report.summary())
    assert report.converged and report.krylov_fallbacks == 0
    assert all(it.krylov_iterations > 0 for it in report.history)


def test_eisenstat_walker_forcing() -> None:
    opts = MultigridOptions(forcing="eisenstat_walker", rtol=1e-10)
    assert eisenstat_walker(1.0, 0.0, 0.0, opts) == opts.ew_max
    # choice 2: 0.9 (0.5)^1.618 = 0.2936 above eta_max = 0.1 -> 0.1
    assert eisenstat_walker(0.5, 1.0, 0.1, opts) == pytest.approx(0.1)
    # fast decrease: 0.9 (1e-3)^1.618 = 1.3e-5, safeguard 0.9 * 0.01^1.618 < 0.1 is not used
    assert eisenstat_walker(1e-3, 1.0, 0.01, opts) == pytest.approx(0.9 * 1e-3 ** opts.ew_alpha)
    # safeguard: gamma eta_prev^alpha = 0.9 * 0.3^1.618 = 0.127 > 0.1 keeps eta up (cap 0.1)
    assert eisenstat_walker(1e-3, 1.0, 0.3, opts) == pytest.approx(0.1)


def test_options_validated(wrinkle) -> None:
    _, energy, _ = wrinkle
    with pytest.raises(InputError, match="linear_method"):
        ShellNewtonSolver(energy, ShellNewtonOptions(linear_method="multigrid"))
    with pytest.raises(InputError, match="ShellNewtonOptions.linear_method"):
        ShellNewtonOptions(linear_method="gmres")
    with pytest.raises(InputError, match="MultigridOptions.forcing"):
        MultigridOptions(forcing="adaptive")
    with pytest.raises(InputError, match="MultigridOptions.rtol"):
        MultigridOptions(rtol=0.0)
    with pytest.raises(InputError, match="MultigridOptions.smoother_degree"):
        MultigridOptions(smoother_degree=0)
    with pytest.raises(InputError, match="MultigridOptions.smoother_pc"):
        MultigridOptions(smoother_pc="ilu")
