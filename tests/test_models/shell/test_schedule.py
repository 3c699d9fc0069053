"""Threaded element kernels (models/shell/schedule.py): race-free bands, same energy."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from meshes.errors import InputError
from meshes.shells import grid_plate
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState
from models.shell.schedule import StencilSchedule, balanced_cuts, vertex_parts
from models.shell.topology import ShellTopology
from solvers.multigrid import MultigridOptions, ShellHierarchy


@pytest.fixture(scope="module")
def plate() -> tuple[ShellTopology, np.ndarray]:
    """A 4-level subdivided 6 x 6 plate (9409 vertices, subdivision vertex order)."""
    hier = ShellHierarchy.build(*grid_plate(6, 6), levels=4)
    return ShellTopology.from_faces(hier.faces, len(hier.vertices)), hier.vertices


@pytest.mark.parametrize("threads", [2, 3])
def test_bands_split_stencils_into_disjoint_chunks_and_a_small_interface(plate, threads) -> None:
    topo, pts = plate
    parts = vertex_parts(topo.faces, topo.n_vertices, threads)
    counts = np.bincount(parts)
    assert counts.size == threads and counts.max() - counts.min() <= 1  # equal bands
    schedule = StencilSchedule.build(topo.hinges, parts)
    everything = np.concatenate([*schedule.chunks, schedule.interface])
    assert np.array_equal(np.sort(everything), np.arange(len(topo.hinges)))
    for t, chunk in enumerate(schedule.chunks):
        assert np.all(parts[topo.hinges[chunk]] == t)  # a chunk writes only its band's rows
    share = schedule.interface.size / len(topo.hinges)
    print(f"{threads} bands: chunks {[c.size for c in schedule.chunks]}, interface "
          f"{schedule.interface.size} ({share:.1%})")
    assert share < 0.03 * (threads - 1)  # O(sqrt n) stencils across the band boundaries


def test_one_thread_is_the_plain_loop(plate) -> None:
    topo, _ = plate
    schedule = StencilSchedule.build(topo.edges, vertex_parts(topo.faces, topo.n_vertices, 1))
    assert schedule.threads == 1 and schedule.interface.size == 0
    assert np.array_equal(schedule.chunks[0], np.arange(len(topo.edges)))


@pytest.mark.parametrize("mode", ["exact", "gauss_newton", "projected"])
def test_threaded_energy_matches_one_thread(plate, mode: str) -> None:
    """Value, gradient and Hessian (edges, hinges, active flip barrier) to round-off."""
    topo, pts = plate
    rest = RestState.from_positions(topo, pts)
    rng = np.random.default_rng(2)
    x = pts * [0.9, 1.0, 1.0] + [0.0, 0.0, 0.01] * rng.standard_normal(pts.shape)
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=0.0, flip_activation=1.0, hessian_mode=mode)
    one = ShellEnergy(topo, rest, params).evaluate(x)
    two = ShellEnergy(topo, rest, replace(params, threads=2)).evaluate(x)
    assert one.terms["flip_barrier"] > 0  # the barrier's kernel adds blocks too
    assert two.value == pytest.approx(one.value, rel=1e-13)
    assert np.allclose(two.grad, one.grad, rtol=0, atol=1e-12 * np.abs(one.grad).max())
    assert two.hess.nnz == one.hess.nnz
    scale = np.abs(one.hess.data).max()
    assert np.abs(two.hess.data - one.hess.data).max() <= 1e-12 * scale
    assert np.array_equal(two.elements["bending"], one.elements["bending"])


def test_balanced_cuts_split_the_work_evenly() -> None:
    indptr = np.concatenate([[0], np.cumsum(np.r_[np.full(50, 10), np.full(50, 1)])])
    cuts = balanced_cuts(indptr, 2)
    assert cuts.tolist() == [0, 28, 100]  # 280 and 270 entries: halves of the work, not rows
    assert balanced_cuts(indptr, 1).tolist() == [0, 100]


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_bad_thread_counts_are_named(bad) -> None:
    with pytest.raises(InputError, match="threads"):
        ShellParams(threads=bad)
    with pytest.raises(InputError, match="MultigridOptions.threads"):
        MultigridOptions(threads=bad)


def test_more_threads_than_vertices_and_disconnected_pieces() -> None:
    """Extremes: 8 threads on two separate triangles (6 vertices); every stencil runs once."""
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0]], float)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    topo = ShellTopology.from_faces(faces, len(pts))
    parts = vertex_parts(topo.faces, topo.n_vertices, 8)
    assert parts.min() >= 0 and parts.max() < 8
    schedule = StencilSchedule.build(topo.edges, parts)
    ran = np.concatenate([*schedule.chunks, schedule.interface])
    assert np.array_equal(np.sort(ran), np.arange(len(topo.edges)))
    rest = RestState.from_positions(topo, pts)
    x = pts * 1.1
    params = ShellParams(k_P=0.0)
    one = ShellEnergy(topo, rest, params).evaluate(x)
    eight = ShellEnergy(topo, rest, replace(params, threads=8)).evaluate(x)
    assert eight.value == pytest.approx(one.value, rel=1e-14)
    assert np.allclose(eight.hess.toarray(), one.hess.toarray(), rtol=1e-14, atol=0)


def test_threaded_newton_solve_keeps_the_serial_history() -> None:
    """A whole multigrid shell Newton solve (exact Hessian, phase space, SBAIJ level
    products) on two threads: the serial solve's iterations, energy and minimiser."""
    import shellcases

    from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver

    hier = ShellHierarchy.build(*grid_plate(6, 6), levels=3)  # 2401 vertices
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=32)
    runs = []
    for threads in (1, 2):
        threaded = ShellEnergy(energy.topology, energy.rest,
                               replace(energy.params, threads=threads),
                               H=energy.penalty_operator.H)
        threaded.set_target(energy.target)
        mg = MultigridOptions(rtol=1e-4, fallback=False, eigen_estimate="solve",
                              level_format="sbaij", phase_space=True, threads=threads)
        opts = ShellNewtonOptions(rtol=1e-9, hessian="exact", far_hessian="gauss_newton",
                                  linear_method="multigrid", multigrid=mg)
        runs.append(ShellNewtonSolver(threaded, opts, hierarchy=hier).minimize(x0))
    (x1, one), (x2, two) = runs
    print(f"one thread: {one.summary()}\ntwo threads: {two.summary()}; max |dx| "
          f"{np.abs(x2 - x1).max():.1e}")
    assert one.converged and two.converged
    assert two.iterations == one.iterations
    assert two.energy == pytest.approx(one.energy, rel=1e-12)
    assert np.abs(x2 - x1).max() < 1e-8
