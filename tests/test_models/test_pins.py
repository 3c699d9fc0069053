"""Two pins holding a shared node: the same motion is fine, different motions are refused."""

from __future__ import annotations

import numpy as np
import pytest

from models.body import PinSpec, pin_conflicts

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
