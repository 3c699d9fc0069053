"""The obstacles' signed gap at given points (t = 0), against hand values."""

from __future__ import annotations

import numpy as np
import pytest

from models.contact import ContactOptions

POINTS = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, -0.5], [3.0, 4.0, 0.0]])


def test_plane_gap_is_the_signed_distance_along_the_unit_normal():
    floor = ContactOptions(obstacle="plane", point=(0.0, 0.0, 1.0), normal=(0.0, 0.0, 2.0))
    assert floor.gap_at(POINTS) == pytest.approx([1.0, -1.5, -1.0])
    assert floor.describe() == "plane through [0.0, 0.0, 1.0] with normal [0.0, 0.0, 1.0]"


def test_sphere_gap_is_the_distance_to_the_centre_minus_the_radius():
    ball = ContactOptions(obstacle="sphere", point=(0.0, 0.0, 0.0), radius=2.5)
    assert ball.gap_at(POINTS) == pytest.approx([-0.5, np.hypot(1.0, 0.5) - 2.5, 2.5])
    assert ball.describe() == "sphere at [0.0, 0.0, 0.0] of radius 2.5"


def test_start_depth_is_the_deepest_node_inside_and_their_count():
    floor = ContactOptions(obstacle="plane", point=(0.0, 0.0, 1.0), normal=(0.0, 0.0, 1.0))
    assert floor.start_depth(POINTS) == (pytest.approx(1.5), 2)
    ball = ContactOptions(obstacle="sphere", point=(0.0, 0.0, 0.0), radius=2.5)
    assert ball.start_depth(POINTS) == (pytest.approx(2.5 - np.hypot(1.0, 0.5)), 2)
    assert ball.start_depth(POINTS[2:]) == (0.0, 0)


def test_start_depth_ignores_round_off_of_nodes_on_the_plane():
    """Nodes on the floor's plane up to 1e-12 of the coordinates' size below it touch it; a
    millionth of a metre below is inside."""
    base = np.array([[0.3, -0.2, -0.01], [0.1, 0.1, -0.01], [0.0, 0.0, 0.5]])
    floor = ContactOptions(obstacle="plane", point=(0.0, 0.0, -0.01), normal=(0.0, 0.0, 1.0))
    assert floor.start_depth(base - [0.0, 0.0, 1.7e-18]) == (0.0, 0)
    assert floor.start_depth(base - [0.0, 0.0, 5e-13]) == (0.0, 0)
    assert floor.start_depth(base - [0.0, 0.0, 1e-6]) == (pytest.approx(1e-6), 2)
