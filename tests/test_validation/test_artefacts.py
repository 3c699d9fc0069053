"""The element-boundary artefact measure (validation.measure) on synthetic energy fields."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError
from validation.measure import (
    coarse_edge_distances,
    edge_band_report,
    segment_distances,
    unique_edges,
    vertex_areas,
)


def grid(n: int, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Right-triangle grid of the square ``[0, size]^2`` in the plane z = 0 (n x n cells)."""
    t = np.linspace(0.0, size, n + 1)
    xx, yy = np.meshgrid(t, t, indexing="ij")
    pts = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return pts, faces.astype(np.int64)


@pytest.fixture(scope="module")
def fine_on_coarse():
    """A fine 96 x 96 grid (the shell) over a coarse 4 x 4 grid (the coarse surface)."""
    fine, fine_faces = grid(96)
    coarse, coarse_faces = grid(4)
    d = coarse_edge_distances(fine, coarse, coarse_faces)
    return fine, vertex_areas(fine, fine_faces), d


def test_segment_distance_analytic():
    """Point-to-segment distances: perpendicular foot inside, and clamped to an end."""
    a, b = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])
    p = np.array([[0.5, 2.0, 0], [3.0, 4.0, 0], [-1.0, 0, 0]])
    assert segment_distances(p, a, b) == pytest.approx([2.0, np.hypot(2, 4), 1.0], abs=1e-15)


def test_coarse_edges_and_areas(fine_on_coarse):
    """4 x 4 coarse grid: 40 axis edges + 16 diagonals; fine areas sum to 1; the farthest
    point from any coarse edge is at distance (1/8)(1 - 1/sqrt 2)... measured on the grid."""
    _, faces = grid(4)
    assert unique_edges(faces).shape == (56, 2)
    _, area, d = fine_on_coarse
    assert area.sum() == pytest.approx(1.0, rel=1e-12)
    # inradius of the coarse right triangle with legs 1/4: (a + b - c)/2
    inradius = (0.25 + 0.25 - 0.25 * np.sqrt(2)) / 2
    assert d.max() <= inradius + 1e-12 and d.max() >= 0.9 * inradius
    assert d.min() == 0.0


def test_uniform_energy_has_ratio_one(fine_on_coarse):
    """Uniform density: F_E = F_A exactly; random density (uniform in [0.5, 1.5]): ratio
    within 3 % of 1 and |correlation| < 0.05."""
    _, area, d = fine_on_coarse
    band = 0.025  # a tenth of the coarse edge
    flat = edge_band_report(d, np.ones_like(d), area, band)
    assert flat.ratio == pytest.approx(1.0, abs=1e-12)
    noisy = edge_band_report(d, np.random.default_rng(0).uniform(0.5, 1.5, d.size), area, band)
    print("uniform:", flat, "noisy:", noisy)
    assert noisy.ratio == pytest.approx(1.0, abs=0.03)
    assert abs(noisy.correlation) < 0.05
    assert 0.1 < flat.area_fraction < 0.6


def test_energy_on_the_edges_has_large_ratio(fine_on_coarse):
    """Band of 1/25 of the coarse edge (area fraction 0.20), density exp(-d^2 / (2 s^2))
    with s = band / 2: most energy inside the band; ratio F_E / F_A > 2.5 and the correlation
    with the distance strongly negative."""
    _, area, d = fine_on_coarse
    band = 0.01
    report = edge_band_report(d, np.exp(-d**2 / (2 * (band / 2) ** 2)), area, band)
    print("on edges:", report)
    assert report.energy_fraction > 0.8
    assert report.ratio > 2.5
    assert report.correlation < -0.5  # measured -0.65


def test_energy_away_from_the_edges_has_small_ratio(fine_on_coarse):
    """Density growing with the distance: ratio < 1, correlation positive."""
    _, area, d = fine_on_coarse
    report = edge_band_report(d, d**2, area, 0.01)
    print("away:", report)
    assert report.ratio < 0.2
    assert report.correlation > 0.7


def test_bad_input_is_refused():
    with pytest.raises(InputError, match="band"):
        edge_band_report(np.ones(3), np.ones(3), np.ones(3), 0.0)
    with pytest.raises(InputError, match="shape"):
        edge_band_report(np.ones(3), np.ones(2), np.ones(3), 1.0)
    with pytest.raises(InputError, match="energy"):
        edge_band_report(np.ones(3), np.zeros(3), np.ones(3), 1.0)


def test_hinge_energies_cross_check():
    """Hinge energies of a randomly displaced closed surface (a subdivided octahedron) sum to
    the bending term of models.shell.bending, and the hinge areas (A1 + A2)/3 partition the
    surface area exactly."""
    from models.embedding.subdivision import SubdivisionOptions, subdivide
    from models.shell.bending import hinge_bending, hinge_weights
    from models.shell.hinge_angle import hinge_angles
    from models.shell.topology import ShellTopology
    from validation.measure import hinge_energies

    verts = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                      [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], dtype=np.int64)
    sub = subdivide(verts, faces, SubdivisionOptions(levels=2, scheme="linear"))
    topo = ShellTopology.from_faces(sub.faces, sub.vertices.shape[0])
    rest = sub.vertices
    x = rest + 0.02 * np.random.default_rng(1).standard_normal(rest.shape)
    k_B = 0.37
    h = hinge_energies(x, rest, topo.hinges, k_B)
    reference = hinge_bending(x, topo.hinges, hinge_angles(rest, topo.hinges),
                              k_B * hinge_weights(rest, topo.hinges), order=0).value
    assert h.energy.sum() == pytest.approx(reference, rel=1e-12)
    assert h.areas.sum() == pytest.approx(vertex_areas(rest, sub.faces).sum(), rel=1e-12)
    assert np.all(h.density >= 0.0)
