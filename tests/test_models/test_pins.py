"""Two pins holding a shared node: the same motion is fine, different motions are refused;
the rigid motions a static body's pins leave free."""

from __future__ import annotations

import numpy as np
import pytest

from models.body import (
    RIGID_MOTIONS,
    PinSpec,
    free_rigid_motions,
    held_components,
    pin_conflicts,
    rigid_motion_gram,
)

# the 3 x 3 x 3 nodes of the unit cube's corners, edges' and faces' midpoints and centre
GRID = np.array([[i, j, k] for i in (0.0, 0.5, 1.0) for j in (0.0, 0.5, 1.0)
                 for k in (0.0, 0.5, 1.0)])
BOTTOM = PinSpec(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0))        # z = 0, clamped
SIDE = PinSpec(point=(0.0, 0.0, 0.0), normal=(1.0, 0.0, 0.0))          # x = 0, clamped


def test_two_clamps_meeting_at_an_edge_do_not_conflict():
    assert pin_conflicts([BOTTOM, SIDE], GRID) == []


def test_a_clamp_and_a_moving_pin_sharing_an_edge_conflict_on_the_moving_component():
    pushed = PinSpec(point=(0.0, 0.0, 0.0), normal=(1.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.1))
    conflicts = pin_conflicts([BOTTOM, pushed], GRID)
    assert [(c.first, c.second, c.component) for c in conflicts] == [(0, 1, 2)]
    shared = GRID[conflicts[0].nodes]
    assert len(shared) == 3 and np.all(shared[:, 0] == 0.0) and np.all(shared[:, 2] == 0.0)


def test_components_held_by_one_pin_only_do_not_conflict():
    pushed_x = PinSpec(point=(0.0, 0.0, 0.0), normal=(1.0, 0.0, 0.0), velocity=(0.1, 0.0, 0.0),
                       components=(0,))
    bottom_z = PinSpec(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), components=(2,))
    assert pin_conflicts([bottom_z, pushed_x], GRID) == []


@pytest.mark.parametrize("other_axis", [False, True])
def test_rotating_pins_agree_only_about_the_same_axis(other_axis):
    """Two box pins on overlapping regions turning about x: the same rotation agrees; a
    rotation about another axis moves the shared nodes differently."""
    turn = PinSpec(box=((0.0, 0.0, 0.0), (1.0, 1.0, 0.5)), point=(0.0, 0.5, 0.5),
                   angular_velocity=(1.0, 0.0, 0.0))
    axis = (0.0, 1.0, 0.0) if other_axis else (1.0, 0.0, 0.0)
    also = PinSpec(box=((0.0, 0.0, 0.5), (1.0, 1.0, 1.0)), point=(0.0, 0.5, 0.5),
                   angular_velocity=axis)
    conflicts = pin_conflicts([turn, also], GRID)
    assert bool(conflicts) == other_axis
    if other_axis:  # the shared nodes: the plane z = 0.5, where the boxes meet
        assert all(np.all(GRID[c.nodes][:, 2] == 0.5) for c in conflicts)


def _free(pins: list[PinSpec], X: np.ndarray = GRID) -> tuple[int, list[str]]:
    """Free rigid motions of ``pins`` on ``X``, rotations about the held nodes' centroid."""
    held = held_components(pins, X)
    center = X[held.any(axis=1)].mean(axis=0)
    return free_rigid_motions(rigid_motion_gram(held, X, center, 1.0))


def plane(normal: tuple[float, float, float], components: tuple[int, ...]) -> PinSpec:
    """The cube's face through the origin with ``normal``, holding ``components``."""
    return PinSpec(point=(0.0, 0.0, 0.0), normal=normal, components=components)


@pytest.mark.parametrize(("pins", "count", "names"), [
    ([BOTTOM], 0, []),                                       # a clamped face
    ([plane((0, 0, 1), (2,))], 3, ["translation along x", "translation along y",
                                   "rotation about z"]),     # a face on rollers
    ([plane((0, 0, 1), (2,)), plane((1, 0, 0), (0,)), plane((0, 1, 0), (1,))], 0, []),
    ([plane((0, 0, 1), (2,)), plane((1, 0, 0), (0,))], 1, ["translation along y"]),
    ([PinSpec(box=((0, 0, 0), (0, 0, 0)))], 3, list(RIGID_MOTIONS[3:])),  # one node
    ([PinSpec(box=((0.5, 0.5, 0), (0.5, 0.5, 1)))], 1, ["rotation about z"]),  # a line
    ([PinSpec(box=((0.5, 0.5, 0), (0.5, 0.5, 1)), components=(0, 1))], 2,
     ["translation along z", "rotation about z"]),
])
def test_the_rigid_motions_pins_leave_free(pins, count, names):
    """Counted from the Gram matrix's null space and named where a motion itself is free: the
    three symmetry planes of a quarter model hold all six, two of them leave the third
    translation, a pinned line the rotation about itself."""
    assert _free(pins) == (count, names)


def test_a_rotation_about_an_axis_off_the_centroid_is_counted_but_not_named():
    """Nodes on the line x = 0.5, y = 0 held in x and y, with a clamped node at (0.5, 1, 0)
    held in z only: the free rotation about z passes through neither the centroid nor the
    origin, a combination of the named motions."""
    line = PinSpec(box=((0.5, 0.0, 0.0), (0.5, 0.0, 1.0)), components=(0, 1))
    node = PinSpec(box=((0.5, 1.0, 0.0), (0.5, 1.0, 0.0)), components=(2,))
    count, names = _free([line, node])
    assert count == 1 and names == []


def test_the_ranks_grams_add_up_to_the_whole_bodys():
    pins = [plane((0, 0, 1), (2,)), PinSpec(box=((0, 0, 1), (1, 0, 1)), components=(0, 1))]
    held, center = held_components(pins, GRID), np.array([0.3, 0.2, 0.1])
    whole = rigid_motion_gram(held, GRID, center, 2.0)
    parts = [rigid_motion_gram(held[k::3], GRID[k::3], center, 2.0) for k in range(3)]
    assert np.allclose(sum(parts), whole, rtol=1e-14, atol=1e-14)
    assert np.allclose(whole, whole.T) and np.linalg.eigvalsh(whole).min() > -1e-12
