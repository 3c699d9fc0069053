"""Stencil-split monolithic Newton (solvers/decomposition/split_newton.py) on one rank.

The 2-rank equality with the serial solve is in
tests/test_solvers/decomposition/test_decomposition_mpi.py.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from models.backend import MPI
from models.shell.energy import ShellParams
from solvers.decomposition.demo import FrameCase, PlateCase, plate_frame, plate_problem, prolong
from solvers.decomposition.split_newton import (
    SplitLayout,
    SplitNewtonSolver,
    rank_of_vertices,
)
from solvers.multigrid import shifted_product
from solvers.shell_newton import ShellNewtonOptions, minimize

CASE = PlateCase(cells=12, compression=0.07, params=ShellParams(penalty_hessian="low_rank"))


def test_layout_numbers_every_unknown_once_inside_its_rank() -> None:
    problem, partition, _ = plate_problem(CASE)
    ranks = 3
    vertex_rank = rank_of_vertices(problem, partition, ranks)
    layout = SplitLayout.build(vertex_rank, problem.H, ranks)
    dofs = (layout.vertex_index[:, None] + np.arange(3)).reshape(-1)
    mults = (layout.cluster_index[:, None] + np.arange(3)).reshape(-1)
    every = np.sort(np.concatenate([dofs, mults]))
    c = problem.H.shape[0]
    assert np.array_equal(every, np.arange(3 * (169 + c)))  # a bijection onto 0..3(n+c)-1
    owner_of = np.searchsorted(layout.offsets, every, side="right") - 1
    expected = np.concatenate([vertex_rank.repeat(3), layout.cluster_rank.repeat(3)])
    order = np.argsort(np.concatenate([dofs, mults]))
    assert np.array_equal(owner_of, expected[order])  # every row inside its rank's range
    print(f"rank sizes {np.diff(layout.offsets)} (vertices {np.bincount(vertex_rank)})")
    assert np.bincount(vertex_rank).min() > 0


def test_split_energy_on_one_rank_equals_shell_energy() -> None:
    problem, partition, x0 = plate_problem(CASE)
    solver = SplitNewtonSolver(problem, partition, comm=MPI.COMM_SELF)
    energy = problem.energy()
    ev, ev_split = energy.evaluate(x0, order=1), solver.energy.evaluate(x0, order=1)
    assert abs(ev_split.value - ev.value) <= 1e-13 * abs(ev.value)
    assert np.abs(ev_split.grad - ev.grad).max() <= 1e-12 * np.abs(ev.grad).max()


def test_split_solve_on_one_rank_equals_serial_augmented_solve() -> None:
    problem, partition, x0 = plate_problem(CASE)
    g0 = float(np.linalg.norm(problem.energy().evaluate(x0, order=1).grad))
    opts = ShellNewtonOptions(rtol=1e-8, gradient_scale=g0)
    x_ref, ref = minimize(problem.energy(), x0, opts)
    solver = SplitNewtonSolver(problem, partition, opts, MPI.COMM_SELF)
    x, rep = solver.minimize(x0)
    print(rep.summary())
    assert rep.converged and rep.iterations == ref.iterations
    assert rep.factorizations == ref.factorizations
    assert abs(rep.energy - ref.energy) <= 1e-12 * abs(ref.energy)
    assert np.abs(x - x_ref).max() < 1e-8
    assert solver.info().symbolic_analyses == 1


def test_split_hessian_product_on_one_rank_is_the_serial_full_hessian() -> None:
    """The product the shift ladder's Lanczos restart runs on: ``(A + G^T G) v``."""
    problem, partition, x0 = plate_problem(CASE)
    solver = SplitNewtonSolver(problem, partition, comm=MPI.COMM_SELF)
    assert solver.newton.hessian_product == solver.linear.hessian_product
    v = np.random.default_rng(3).standard_normal(x0.size)
    split = solver.newton.hessian_product(solver.energy.evaluate(x0), v)
    ev = problem.energy().evaluate(x0)
    serial = shifted_product(ev, 0.0, v)
    assert np.abs(split - serial).max() <= 1e-13 * np.abs(serial).max()
    assert np.abs(serial - ev.hess @ v).max() > 1e-5 * np.abs(serial).max()  # G^T G counts


def test_prolong_reproduces_bilinear_fields() -> None:
    """Grid sequencing's interpolation is exact for fields bilinear in (x, y)."""
    coarse, _, _ = plate_problem(replace(CASE, cells=6))
    fine, _, _ = plate_problem(replace(CASE, cells=18))

    def field(p: np.ndarray) -> np.ndarray:
        return np.column_stack([1 + p[:, 0] * p[:, 1], p[:, 0] - 2 * p[:, 1], p[:, 1] ** 0])

    rest_c, rest_f = coarse.rest.positions, fine.rest.positions
    assert np.abs(prolong(field(rest_c), 6, 18) - field(rest_f)).max() < 1e-14


def test_frame_start_is_the_previous_state_moved_with_the_target() -> None:
    fc = FrameCase(plate=CASE, increment=0.01)
    _, _, x_prev = plate_problem(CASE)
    problem, _, x_start = plate_frame(fc, x_prev)
    before, _, _ = plate_problem(CASE)
    moved = x_start - x_prev
    assert np.allclose(moved, problem.target - before.target, atol=0, rtol=0)
    # the new target is compressed 1 % more along x: x-extent 0.93 -> 0.92
    span = problem.target[:, 0].max() - problem.target[:, 0].min()
    assert abs(span - 0.92) < 1e-14
