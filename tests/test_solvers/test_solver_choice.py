"""The linear method and thread count a scene gets when it leaves them to the code."""

from __future__ import annotations

import pytest

from meshes.errors import InputError
from solvers import solver_choice
from solvers.solver_choice import (
    MULTIGRID_FROM_LEVELS,
    MULTIGRID_FROM_VERTICES,
    MULTIGRID_STATIC_FROM_LEVELS,
    PHASE_SPACE_FROM_VERTICES,
    RANKS_FROM_BODY_WORK,
    RANKS_FROM_WORK,
    THREADS_FROM_VERTICES,
    WORK_PER_RANK,
    WRINKLED_FROM_EDGES,
    choose_linear_method,
    choose_phase_space,
    choose_ranks,
    choose_threads,
    wrinkled_start,
)


@pytest.mark.parametrize(("vertices", "expected"), [
    (0, "direct"), (650, "direct"), (MULTIGRID_FROM_VERTICES - 1, "direct"),
    (MULTIGRID_FROM_VERTICES, "multigrid"), (2610, "multigrid"), (41730, "multigrid")])
@pytest.mark.parametrize(("levels", "static"), [(1, True), (2, True), (2, False)])
def test_auto_picks_the_method_by_size_on_both_sides_of_the_crossover(vertices, expected, levels,
                                                                      static):
    assert choose_linear_method("auto", vertices, levels, static=static) == expected


@pytest.mark.parametrize(("vertices", "expected"), [
    (2610, False), (5218, False), (PHASE_SPACE_FROM_VERTICES - 1, False),
    (PHASE_SPACE_FROM_VERTICES, True), (10434, True), (41730, True)])
def test_the_phase_space_is_chosen_by_size_on_both_sides_of_the_crossover(vertices, expected):
    """Measured over imperfection seeds (docs/notes/phase-space.md): the wrinkle scenes at
    2 610 - 5 218 vertices take less CPU without it, at 10 434 and 41 730 with it."""
    assert choose_phase_space(vertices) is expected


@pytest.mark.parametrize(("offset", "expected"), [
    (0.0, False), (0.99 * WRINKLED_FROM_EDGES, False), (WRINKLED_FROM_EDGES, True),
    (3.0, True)])
def test_a_start_counts_as_wrinkled_by_its_offset_in_edge_lengths(offset, expected):
    for edge in (1e-3, 0.05):
        assert wrinkled_start(offset * edge, edge) is expected


@pytest.mark.parametrize(("levels", "expected"), [
    (0, "direct"), (MULTIGRID_FROM_LEVELS - 1, "direct"), (MULTIGRID_FROM_LEVELS, "multigrid"),
    (4, "multigrid")])
def test_auto_needs_a_deep_enough_hierarchy_in_a_dynamic_scene(levels, expected):
    """One level (the bunny scene: 12 534 vertices) leaves a coarse solve of a quarter of the
    unknowns, where multigrid-CG was measured slower than the direct solve in an impact."""
    assert choose_linear_method("auto", 12534, levels, static=False) == expected


@pytest.mark.parametrize(("levels", "expected"), [
    (0, "direct"), (MULTIGRID_STATIC_FROM_LEVELS, "multigrid"), (2, "multigrid")])
def test_a_load_sequence_takes_multigrid_from_one_level(levels, expected):
    """A static external mesh at one level (the sfepy elbow closed, 3 358 vertices; the cinolib
    sphere squeezed, 5 762) solves 1.4-1.5x faster by multigrid-CG (docs/notes/
    solver-choice.md); with no level there is no hierarchy at all."""
    assert MULTIGRID_STATIC_FROM_LEVELS == 1
    assert choose_linear_method("auto", 3358, levels, static=True) == expected


@pytest.mark.parametrize("method", ["direct", "multigrid"])
@pytest.mark.parametrize(("vertices", "levels"), [(10, 0), (10**6, 4)])
def test_a_named_method_is_kept_at_every_size(method, vertices, levels):
    for static in (True, False):
        assert choose_linear_method(method, vertices, levels, static=static) == method


def test_an_unknown_method_is_refused_by_its_key():
    with pytest.raises(InputError, match=r"shell.solver.method.*'cholmod'"):
        choose_linear_method("cholmod", 100, 2, static=True)


def test_auto_threads_are_the_cores_of_a_large_serial_shell_else_one(monkeypatch):
    monkeypatch.setattr(solver_choice, "available_cores", lambda: 6)
    big, small = THREADS_FROM_VERTICES, THREADS_FROM_VERTICES - 1
    assert choose_threads(0, ranks=1, vertices=big) == 6
    assert choose_threads(0, ranks=1, vertices=small) == 1
    assert choose_threads(0, ranks=2, vertices=big) == 1
    assert choose_threads(3, ranks=1, vertices=small) == 3
    assert choose_threads(3, ranks=4, vertices=big) == 3  # a count written by the user is kept


@pytest.mark.parametrize(("work", "cores", "expected"), [
    (3126, 2, 1), (RANKS_FROM_WORK - 1, 2, 1), (RANKS_FROM_WORK, 2, 2), (68574, 2, 2),
    (42246, 2, 2), (42246, 1, 1), (RANKS_FROM_WORK, 8, 2), (42246, 64, 8)])
def test_a_serial_command_of_a_large_frame_takes_the_cores_as_ranks(work, cores, expected):
    """Ranks on both sides of the crossover, at most one per WORK_PER_RANK (the default
    bar 3 126, the bunny's drop 68 574, the bar at 4 levels 42 246)."""
    assert RANKS_FROM_WORK // WORK_PER_RANK == 2
    assert choose_ranks(0, work, cores) == expected


@pytest.mark.parametrize(("work", "expected"), [
    (10938, 1), (12606, 1), (RANKS_FROM_BODY_WORK - 1, 1), (RANKS_FROM_BODY_WORK, 2),
    (27030, 2), (56040, 2)])
def test_a_body_alone_takes_ranks_from_a_larger_frame(work, expected):
    """The external meshes dropped without a skin (docs/notes/solver-choice.md): the elbow
    (5 469 dofs x 2) and the plate (6 303 x 2) stay, the ball (13 515 x 2) and the bunny
    (14 010 x 4) go; with a shell the same frames would go."""
    assert choose_ranks(0, work, 2, shell=False) == expected
    assert choose_ranks(0, work, 2) == 2


def test_named_threads_keep_one_process():
    assert choose_ranks(1, 41730, 2) == 1
    assert choose_ranks(2, 41730, 2) == 1


def test_available_cores_follows_the_affinity_mask(monkeypatch):
    monkeypatch.setattr(solver_choice.os, "sched_getaffinity", lambda pid: {0, 5, 7})
    assert solver_choice.available_cores() == 3


def test_negative_threads_are_refused():
    with pytest.raises(InputError, match="shell.solver.threads"):
        choose_threads(-1, ranks=1, vertices=10**5)
