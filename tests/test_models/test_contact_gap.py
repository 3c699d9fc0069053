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
