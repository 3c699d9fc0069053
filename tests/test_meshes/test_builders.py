"""gmsh builders: volumes (exact, converging at rate 2), closed outward boundary, sofa."""

from __future__ import annotations

import math
from pathlib import Path

import gmsh
import numpy as np
import pytest

from meshes import SofaDimensions, TetMesh, box, cylinder, sofa, sofa_parts, sphere, validate
from meshes.builders import Box
from meshes.errors import InputError


@pytest.fixture(autouse=True)
def _private_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WRINKLES_CACHE", str(tmp_path / "cache"))


def divergence_volume(m: TetMesh) -> float:
    """Volume from the boundary: sum_f (centroid . n_f) area_f / 3 (divergence theorem)."""
    p = m.points[m.boundary]
    area_normal = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return float(np.einsum("ij,ij->", p.mean(axis=1), area_normal) / 3.0)


def boundary_edge_length(m: TetMesh) -> float:
    """Mean length of the boundary triangles' distinct edges (the measured surface h)."""
    f = m.boundary
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1),
                  axis=0)
    return float(np.linalg.norm(m.points[e[:, 0]] - m.points[e[:, 1]], axis=1).mean())


def assert_closed_outward(m: TetMesh) -> None:
    assert validate(m) is m
    assert m.volumes.min() > 0
    assert abs(divergence_volume(m) - m.volume) <= 1e-10 * m.volume
    assert m.n_components == 1


def union_volume(parts: tuple[Box, ...]) -> float:
    """Exact volume of a union of axis-aligned boxes by coordinate compression."""
    lo = np.array([p.origin for p in parts])
    hi = lo + np.array([p.size for p in parts])
    grids = [np.unique(np.concatenate([lo[:, a], hi[:, a]])) for a in range(3)]
    mids = [0.5 * (g[1:] + g[:-1]) for g in grids]
    cx, cy, cz = np.meshgrid(*mids, indexing="ij")
    centres = np.stack([cx, cy, cz], axis=-1)[..., None, :]
    covered = ((centres > lo) & (centres < hi)).all(axis=-1).any(axis=-1)
    dx, dy, dz = np.meshgrid(*[np.diff(g) for g in grids], indexing="ij")
    return float((covered * dx * dy * dz).sum())


def test_box_volume_exact_and_closed() -> None:
    m = box(0.6, 1.4, 0.3, 0.15, origin=(1.0, -2.0, 0.5))
    assert abs(m.volume - 0.6 * 1.4 * 0.3) <= 1e-12
    assert_closed_outward(m)
    np.testing.assert_allclose(m.bbox[0], [1.0, -2.0, 0.5], atol=1e-14)
    np.testing.assert_allclose(m.bbox[1], [1.6, -0.6, 0.8], atol=1e-14)
    assert m.source == "box(lx=0.6, ly=1.4, lz=0.3, h=0.15, origin=(1.0, -2.0, 0.5))"
    assert 0.5 * 0.15 < m.mean_edge_length < 1.2 * 0.15


@pytest.mark.parametrize(("name", "build", "hs"), [
    ("box", lambda h: box(1.0, 1.0, 1.0, h), (1.0, 0.5, 0.25, 0.125)),
    ("sphere", lambda h: sphere(1.0, h), (0.8, 0.4, 0.2)),
    ("sofa", lambda h: sofa(h=h), (0.4, 0.2, 0.1)),
])
def test_h_sets_the_edge_length(name: str, build, hs: tuple[float, ...]) -> None:
    """Regression: OCC point sizes (~bbox/5) used to cap the size, so h > 0.2 did nothing."""
    edges = np.array([build(h).mean_edge_length for h in hs])
    slope = np.polyfit(np.log(hs), np.log(edges), 1)[0]
    print(f"{name}: h={hs}, mean edge / h={np.round(edges / np.array(hs), 3)}, slope={slope:.3f}")
    assert np.all((0.7 < edges / np.array(hs)) & (edges / np.array(hs) < 1.4))
    assert 0.6 < slope < 1.2  # coarse h is limited by features (0.2 m arms): sofa 0.68


def test_beam_box() -> None:
    m = box(2.0, 0.2, 0.2, 0.1)
    assert abs(m.volume - 0.08) <= 1e-12
    assert_closed_outward(m)


@pytest.mark.parametrize(("name", "build", "exact"), [
    ("sphere", lambda h: sphere(1.0, h), 4.0 / 3.0 * math.pi),
    ("cylinder", lambda h: cylinder(1.0, 1.0, h), math.pi),
])
def test_curved_volume_converges_at_rate_two(name: str, build, exact: float) -> None:
    hs = np.array([0.2, 0.14, 0.1])
    meshes = [build(h) for h in hs]
    for m in meshes:
        assert_closed_outward(m)
    errors = np.array([exact - m.volume for m in meshes])
    assert (errors > 0).all()  # inscribed polyhedra: volume from below
    rate_h = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    measured = np.array([boundary_edge_length(m) for m in meshes])
    rate_measured = np.polyfit(np.log(measured), np.log(errors), 1)[0]
    print(f"{name}: h={hs}, errors={errors}, rate(h)={rate_h:.3f}, "
          f"rate(boundary edge)={rate_measured:.3f}")
    assert 1.8 < rate_h < 2.2
    assert 1.85 < rate_measured < 2.15
    assert errors[-1] < 0.01 * exact


def test_cylinder_axis_and_sphere_center() -> None:
    c = cylinder(0.3, 1.2, 0.1, axis=(0.0, 2.0, 0.0))
    assert c.bbox[0][1] == 0.0 and c.bbox[1][1] == pytest.approx(1.2, abs=1e-12)
    surface = c.points[np.unique(c.boundary)]
    lateral = surface[(surface[:, 1] > 1e-9) & (surface[:, 1] < 1.2 - 1e-9)]
    np.testing.assert_allclose(np.hypot(lateral[:, 0], lateral[:, 2]), 0.3, rtol=1e-9)
    assert np.hypot(c.points[:, 0], c.points[:, 2]).max() <= 0.3 * (1 + 1e-9)
    assert cylinder(0.3, 1.2, 0.1, axis="y").source.endswith("axis=(0.0, 1.0, 0.0))")
    s = sphere(0.5, 0.2, center=(1.0, 2.0, 3.0))
    radii = np.linalg.norm(s.points[np.unique(s.boundary)] - [1.0, 2.0, 3.0], axis=1)
    np.testing.assert_allclose(radii, 0.5, rtol=1e-9)


def test_sofa_is_one_solid_with_the_union_volume() -> None:
    m = sofa(h=0.15)
    assert_closed_outward(m)
    exact = union_volume(sofa_parts())
    d = SofaDimensions()
    by_hand = 2.0 * d.depth * d.seat_height + 2.0 * d.back_thickness * (
        d.back_height - d.seat_height) + 2 * d.arm_thickness * (d.depth - d.back_thickness) * (
        d.arm_height - d.seat_height)
    assert exact == pytest.approx(by_hand, rel=1e-14)
    assert abs(m.volume - exact) <= 1e-10 * exact
    lo, hi = m.bbox
    np.testing.assert_allclose(lo, [0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(hi, [2.0, 0.9, 0.85], atol=1e-12)
    top_of_arm = m.points[(m.points[:, 0] < 0.2) & (m.points[:, 1] < 0.5)][:, 2].max()
    assert top_of_arm == pytest.approx(0.65, abs=1e-12)


def test_sofa_width_and_dimensions() -> None:
    dims = SofaDimensions(depth=1.0, arm_thickness=0.25)
    m = sofa(width=2.6, h=0.2, dims=dims)
    assert m.bbox[1][0] == pytest.approx(2.6, abs=1e-12)
    assert abs(m.volume - union_volume(sofa_parts(2.6, dims))) <= 1e-10 * m.volume
    assert m.n_components == 1


def test_builders_work_repeatedly_and_inside_a_user_gmsh_session() -> None:
    first = box(1.0, 1.0, 1.0, 0.5, cache=False)
    second = box(1.0, 1.0, 1.0, 0.5, cache=False)
    np.testing.assert_array_equal(first.points, second.points)
    np.testing.assert_array_equal(first.tets, second.tets)
    assert not gmsh.isInitialized()
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.model.add("user")
        models = gmsh.model.list()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 7.0)
        gmsh.option.setNumber("General.Verbosity", 3)
        inside = box(1.0, 1.0, 1.0, 0.5, cache=False)
        assert gmsh.isInitialized() and gmsh.model.list() == models
        assert gmsh.model.getCurrent() == "user"
        assert gmsh.option.getNumber("Mesh.MeshSizeMax") == 7.0
        assert gmsh.option.getNumber("General.Verbosity") == 3
    finally:
        gmsh.finalize()
    np.testing.assert_array_equal(inside.tets, first.tets)


@pytest.mark.parametrize(("call", "message"), [
    (lambda: box(1.0, -1.0, 1.0, 0.1), r"box: ly must be finite and > 0, got -1\.0"),
    (lambda: box(1.0, 1.0, 1.0, float("nan")), r"box: h must be finite and > 0"),
    (lambda: box(1.0, 1.0, 1.0, 0.1, origin=(0, 0)), r"box: origin must be 3 finite numbers"),
    (lambda: sphere(1.0, 1e-3), r"sphere: h=0\.001 would give ~3\.56e\+10 tets"),
    (lambda: cylinder(1.0, 1.0, 0.2, axis="w"), r"cylinder: axis must be 'x', 'y', 'z'"),
    (lambda: cylinder(1.0, 1.0, 0.2, axis=(0, 0, 0)), r"cylinder: axis must be non-zero"),
    (lambda: sofa(width=0.3), r"sofa: width must exceed 2 \* arm_thickness = 0\.4"),
    (lambda: SofaDimensions(arm_height=0.9), r"seat_height < arm_height < back_height"),
    (lambda: SofaDimensions(depth=0.0), r"SofaDimensions\.depth must be finite and > 0"),
])
def test_builder_input_errors(call, message: str) -> None:
    with pytest.raises(InputError, match=message):
        call()
