"""Shell Newton/SQP: quadratic convergence, penalty solve paths, failure reporting."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from meshes.errors import InputError
from meshes.shells import grid_plate, wrap_on_cylinder
from models.embedding.clusters import ClusterOptions, build_clusters
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState
from models.shell.topology import ShellTopology
from solvers.linear import LinearSolverOptions, ShiftOptions
from solvers.shell_newton import (
    GROWTH_FROM_VERTICES,
    ShellNewtonOptions,
    ShellNewtonSolver,
    ShellSolveError,
    minimize,
    step_growth,
)


def bent_plate_energy(penalty_hessian: str = "assembled") -> tuple[ShellEnergy, np.ndarray]:
    """8x8 plate held by 9 clusters to its own shape rolled on a cylinder of radius 0.6."""
    pts, faces = grid_plate(8, 8)
    topo = ShellTopology.from_faces(faces, len(pts))
    clusters = build_clusters(pts, faces, ClusterOptions(count=9))
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, penalty_hessian=penalty_hessian)
    energy = ShellEnergy(topo, RestState.from_positions(topo, pts), params, H=clusters.H)
    energy.set_target(wrap_on_cylinder(pts, 0.6))
    return energy, pts


def test_quadratic_convergence(rng: np.random.Generator) -> None:
    energy, pts = bent_plate_energy()
    x_star, first = minimize(energy, pts, ShellNewtonOptions(rtol=1e-10))
    assert first.converged
    x0 = x_star + 1e-2 * rng.standard_normal(x_star.shape)  # inside the Newton basin
    x, report = minimize(energy, x0, ShellNewtonOptions(rtol=1e-13, max_iterations=30))
    g = report.grad_norms
    print("gradient norms:", " ".join(f"{v:.3e}" for v in g))
    print("g_{k+1}/g_k^2:", " ".join(f"{v:.3e}" for v in g[1:] / g[:-1] ** 2))
    assert report.converged and report.iterations <= 12
    # pairs (g_k, g_{k+1}) whose g_{k+1} is above the round-off floor 1e-12 g_0 (the final
    # step lands on ~1e-11 = 1e-15 g_0 whatever the ratio, so it says nothing about the rate)
    above = np.flatnonzero(g[1:] > 1e-12 * g[0])[-3:]
    gk, gk1 = g[above], g[above + 1]
    ratios = gk1 / gk**2
    slope = np.polyfit(np.log(gk), np.log(gk1), 1)[0]
    print(f"last three C_k = {ratios}, fitted log-slope {slope:.3f}")
    assert above.size == 3 and above[-1] >= len(g) - 3
    # a linearly convergent method would have C_k = g_{k+1}/g_k^2 growing like 1/g_k (~1e5 at
    # g_k ~ 1e-5); Newton keeps it bounded and modest
    assert np.all(ratios < 0.5)
    assert 1.6 < slope < 2.6
    assert all(it.step == 1.0 and it.shift == 0.0 for it in report.history[-4:])
    assert np.max(np.abs(x - x_star)) < 1e-8


def test_low_rank_penalty_matches_assembled() -> None:
    assembled, pts = bent_plate_energy("assembled")
    low_rank, _ = bent_plate_energy("low_rank")
    xa, ra = minimize(assembled, pts, ShellNewtonOptions(rtol=1e-11))
    xl, rl = minimize(low_rank, pts, ShellNewtonOptions(rtol=1e-11))
    print(f"assembled: {ra.summary()}\nlow rank : {rl.summary()}")
    assert ra.converged and rl.converged
    assert ra.iterations == rl.iterations
    assert np.max(np.abs(xa - xl)) < 1e-9
    assert abs(ra.energy - rl.energy) < 1e-12 * ra.energy


@pytest.mark.parametrize("linear", [LinearSolverOptions(backend="scipy"),
                                    LinearSolverOptions(backend="mumps", symmetric="ldlt",
                                                        matrix_format="sbaij"),
                                    LinearSolverOptions(backend="petsc")],
                         ids=["scipy", "mumps-ldlt-sbaij", "petsc"])
def test_backends_reach_the_same_minimum(linear: LinearSolverOptions) -> None:
    energy, pts = bent_plate_energy()
    x_ref, ref = minimize(energy, pts, ShellNewtonOptions(rtol=1e-11))
    x, report = minimize(energy, pts, ShellNewtonOptions(rtol=1e-11, linear=linear))
    print(f"{linear.backend}: {report.summary()}")
    assert report.converged and np.max(np.abs(x - x_ref)) < 1e-9


def test_solver_reuses_analysis_across_frames() -> None:
    energy, pts = bent_plate_energy()
    solver = ShellNewtonSolver(energy, ShellNewtonOptions(rtol=1e-10))
    x1, r1 = solver.minimize(pts)
    energy.set_target(wrap_on_cylinder(pts, 0.7))  # next frame: new target, warm start
    x2, r2 = solver.minimize(x1)
    stats = solver.linear.plain.stats  # type: ignore[union-attr]
    analyses = sum(1 for h in stats.history if not h.reused_analysis)
    print(f"frame 1 {r1.iterations} it, frame 2 {r2.iterations} it, factorisations "
          f"{stats.factorizations}, symbolic analyses {analyses}")
    assert r1.converged and r2.converged and analyses == 1
    assert stats.factorizations == r1.factorizations + r2.factorizations
    # report times are per call, the solver's stats accumulate over both frames
    total = stats.analysis_time + stats.numeric_time
    assert r2.time_factorize < total and r2.time_analysis == 0.0
    assert r1.time_factorize + r2.time_factorize == pytest.approx(total, rel=1e-9)
    assert r2.iterations < r1.iterations  # the warm start helps


class WrongGradientEnergy:
    """W = |x|^2 but reports grad = -2x: no step along -H^{-1} g can decrease W."""

    n_vertices = 4

    def value(self, x: np.ndarray) -> float:
        return float(np.sum(np.asarray(x) ** 2))

    def evaluate(self, x: np.ndarray, order: int = 2, hessian: str | None = None):
        from models.shell.energy import ShellEval
        v = np.asarray(x, dtype=float).reshape(-1)
        return ShellEval(value=self.value(x), grad=-2.0 * v,
                         hess=sp.identity(12, format="csr") * 2.0, penalty_factor=None)


def test_no_progress_raises_with_best_state() -> None:
    x0 = np.arange(12.0).reshape(4, 3)
    opts = ShellNewtonOptions(shift=ShiftOptions(max_shifts=3), max_line_search=5,
                              linear=LinearSolverOptions(backend="scipy"))
    with pytest.raises(ShellSolveError) as info:
        minimize(WrongGradientEnergy(), x0, opts)
    err = info.value
    print(err)
    assert np.array_equal(err.x, x0) and not err.report.converged
    assert err.report.iterations == 0 and "no Armijo step" in str(err)


class PlateauEnergy:
    """W = 1 everywhere but grad = g0 != 0 (largest at vertex 2), Hessian I: every Newton step
    is accepted only inside the round-off allowance and changes neither W nor g."""

    n_vertices = 4
    g0 = np.array([0.1, 0.0, 0.0, 0.0, 0.2, 0.0, 0.3, 0.4, 0.5, 0.0, 0.0, 0.1])

    def value(self, x: np.ndarray) -> float:
        return 1.0

    def evaluate(self, x: np.ndarray, order: int = 2, hessian: str | None = None):
        from models.shell.energy import ShellEval
        return ShellEval(value=1.0, grad=self.g0.copy(), hess=sp.identity(12, format="csr"),
                         penalty_factor=None)


@pytest.mark.parametrize("k", [1, 5])
def test_stagnation_stops_naming_worst_vertex(k: int) -> None:
    opts = ShellNewtonOptions(stagnation_iterations=k, max_iterations=50,
                              linear=LinearSolverOptions(backend="scipy"))
    with pytest.raises(ShellSolveError) as info:
        minimize(PlateauEnergy(), np.zeros((4, 3)), opts)
    err, report = info.value, info.value.report
    print(err)
    # Armijo inside 16 eps |W| needs c1 alpha |g|^2 <= 3.55e-15: |g|^2 = 0.56, alpha = 2^-34
    assert report.reason == "stagnation" and report.iterations == k and not report.converged
    assert all(it.line_search_steps == 34 for it in report.history)
    assert "vertex 2 (|g_i| = 7.071e-01)" in str(err)  # |(0.3, 0.4, 0.5)| = sqrt(0.5)
    assert np.all(report.energies == 1.0) and np.all(np.isfinite(err.x))


def test_max_iterations_returns_best_state() -> None:
    energy, pts = bent_plate_energy()
    x, report = minimize(energy, pts, ShellNewtonOptions(rtol=1e-12, max_iterations=3))
    assert not report.converged and report.reason == "max_iterations"
    assert report.iterations == 3
    assert np.all(np.diff(report.energies) < 0)  # every accepted step decreased W
    assert report.energy == pytest.approx(energy.value(x), rel=1e-14)


def test_option_validation() -> None:
    with pytest.raises(InputError, match="ShellNewtonOptions.hessian"):
        ShellNewtonOptions(hessian="newton")
    with pytest.raises(InputError, match="ShellNewtonOptions.armijo_c1"):
        ShellNewtonOptions(armijo_c1=0.7)
    with pytest.raises(InputError, match="ShellNewtonOptions.augmented_linear"):
        ShellNewtonOptions(augmented_linear=LinearSolverOptions(symmetric="cholesky"))
    with pytest.raises(InputError, match="ShellNewtonOptions.max_iterations"):
        ShellNewtonOptions(max_iterations=0)
    with pytest.raises(InputError, match="ShellNewtonOptions.stagnation_iterations"):
        ShellNewtonOptions(stagnation_iterations=0)
    with pytest.raises(InputError, match="x0"):
        minimize(bent_plate_energy()[0], np.zeros((3, 3)))


class DoubleWellEnergy:
    """``W = sum_i t_i^4 / 4 - t_i^2 + 0.1 t_i`` over the 12 coordinates: Hessian ``diag(3 t^2
    - 2)``, so at ``t = 0`` every eigenvalue is -2 (the shift must exceed 2); the tilt makes
    the minimum ``t ~ -1.46`` unique among those the shifted steps reach from 0."""

    n_vertices = 4

    def value(self, x: np.ndarray) -> float:
        t = np.asarray(x, dtype=float).reshape(-1)
        return float(np.sum(t**4 / 4 - t**2 + 0.1 * t))

    def evaluate(self, x: np.ndarray, order: int = 2, hessian: str | None = None):
        from models.shell.energy import ShellEval
        t = np.asarray(x, dtype=float).reshape(-1)
        return ShellEval(value=self.value(x), grad=t**3 - 2 * t + 0.1,
                         hess=sp.diags(3 * t**2 - 2).tocsr(), penalty_factor=None)


def test_a_solve_starts_its_shifts_where_the_previous_first_iteration_needed_them() -> None:
    """Two frames from the same indefinite start: the second pays two factorisations in its
    first iteration (one rung below, then the same shift) instead of the ladder's climb from
    zero, and reaches the same minimum; a convex start then takes the rung below at once."""
    solver = ShellNewtonSolver(DoubleWellEnergy(), ShellNewtonOptions(rtol=1e-10))
    x0 = np.zeros((4, 3))
    x1, first = solver.minimize(x0)
    x2, second = solver.minimize(x0)
    climb = first.history[0].factorizations
    print(f"first iteration: {climb} factorisations (tau {first.history[0].shift:.3g}), then "
          f"{second.history[0].factorizations} (tau {second.history[0].shift:.3g}); "
          f"its {first.iterations} / {second.iterations}, factorisations "
          f"{first.factorizations} / {second.factorizations}")
    assert first.converged and second.converged
    assert climb >= 7 and first.history[0].shift > 2.0  # 0, 2e-6, ..., past |lambda| = 2
    assert second.history[0].factorizations == 2
    assert second.history[0].shift == pytest.approx(first.history[0].shift, rel=1e-14)
    assert second.factorizations <= first.factorizations - (climb - 2)
    assert np.allclose(x1, x2, atol=1e-9) and np.all(x1 < -1.4)
    x3, third = solver.minimize(x2 + 0.05)  # a convex start: accepted one rung lower
    growth = solver.options.shift.growth
    assert third.converged and np.allclose(x3, x2, atol=1e-9)
    assert third.history[0].factorizations == 1
    assert third.history[0].shift == pytest.approx(second.history[0].shift / growth, rel=1e-14)


def test_shifted_steps_passing_in_full_are_lengthened_while_the_energy_falls() -> None:
    """The double well from its maximum: the shifts 20, 10, 5 leave steps 8x too short;
    ``step_growth = 8`` doubles them to 8x (each a lower W), the unshifted tail keeps
    ``alpha <= 1``; the same minimum in fewer iterations than plain backtracking."""
    reports = {}
    for growth in (1, 8):
        solver = ShellNewtonSolver(DoubleWellEnergy(), ShellNewtonOptions(
            rtol=1e-10, step_growth=growth, shift_decay=2))
        x, reports[growth] = solver.minimize(np.zeros((4, 3)))
        assert reports[growth].converged and np.all(x < -1.4)
    plain, longer = reports[1], reports[8]
    print("steps", [h.step for h in longer.history], "shifts", [h.shift for h in longer.history],
          f"its {longer.iterations} against {plain.iterations}")
    assert all(h.step <= 1.0 for h in plain.history)
    assert [h.step for h in longer.history[:3]] == [8.0, 8.0, 8.0]
    assert all(h.step <= 1.0 for h in longer.history if h.shift == 0.0)
    assert longer.energy == pytest.approx(plain.energy, rel=1e-14)
    assert longer.iterations < plain.iterations


def test_step_growth_by_size() -> None:
    """0 lengthens shifted steps up to 8x from 20 000 shell vertices; a given factor is kept."""
    assert [step_growth(0, n) for n in (GROWTH_FROM_VERTICES - 1, GROWTH_FROM_VERTICES)] == [1, 8]
    assert step_growth(4, 10) == 4 and step_growth(1, 10 ** 6) == 1
    with pytest.raises(InputError, match="ShellNewtonOptions.step_growth"):
        ShellNewtonOptions(step_growth=-1)
