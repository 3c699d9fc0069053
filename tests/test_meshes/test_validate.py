"""Validation of tet meshes from arrays: structure, geometry, manifoldness, fuzzing."""

from __future__ import annotations

import re
from collections import Counter
from itertools import combinations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from meshes import (
    MeshWarning,
    TetMesh,
    ValidationOptions,
    boundary_faces_with_cells,
    boundary_surface,
    boundary_triangles,
    structured_box,
    tet_components,
    validate,
)
from meshes.errors import InputError
from meshes.tetmesh import group_rows


def divergence_volume(points: np.ndarray, faces: np.ndarray) -> float:
    """Volume from the boundary: sum_f (centroid . n_f) area_f / 3 (divergence theorem)."""
    p = points[faces]
    area_normal = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return float(np.einsum("ij,ij->", p.mean(axis=1), area_normal) / 3.0)


def two_cubes(offset: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Two unit Kuhn cubes, the second shifted by ``offset``, coincident points merged."""
    a = structured_box((1, 1, 1))
    b = structured_box((1, 1, 1), origin=offset)
    points = np.concatenate([a.points, b.points])
    _, first, inverse = np.unique(points.round(12), axis=0, return_index=True,
                                  return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    tets = rank[inverse.reshape(-1)][np.concatenate([a.tets, b.tets + a.n_points])]
    return points[first[order]], tets


def test_single_tet_boundary_is_outward() -> None:
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = boundary_triangles(np.array([[0, 1, 2, 3]]))
    assert faces.shape == (4, 3)
    for f in faces:
        opposite = points[({0, 1, 2, 3} - set(f.tolist())).pop()]
        n = np.cross(points[f[1]] - points[f[0]], points[f[2]] - points[f[0]])
        assert n @ (points[f[0]] - opposite) > 0
    assert divergence_volume(points, faces) == pytest.approx(1.0 / 6.0, rel=1e-14)


def test_structured_box_volume_boundary_and_divergence() -> None:
    m = structured_box((3, 2, 4), size=(1.5, 0.5, 2.0), origin=(-1.0, 2.0, 0.5))
    assert m.n_tets == 6 * 24 and m.n_points == 4 * 3 * 5
    np.testing.assert_allclose(m.volumes, 1.5 * 0.5 * 2.0 / 144, rtol=1e-12)
    assert m.boundary.shape[0] == 2 * 2 * (3 * 2 + 2 * 4 + 3 * 4)
    assert abs(divergence_volume(m.points, m.boundary) - 1.5) <= 1e-10 * 1.5
    np.testing.assert_array_equal(m.bbox[0], [-1.0, 2.0, 0.5])
    np.testing.assert_allclose(m.bbox[1], [0.5, 2.5, 2.5], rtol=1e-15)
    nodes, faces = boundary_surface(m.tets)
    np.testing.assert_array_equal(nodes[faces], m.boundary)
    assert nodes.size == m.n_points - 2 * 1 * 3  # interior nodes: (3-1)(2-1)(4-1) = 6


def test_validate_returns_same_mesh_when_clean() -> None:
    m = structured_box((2, 2, 2))
    assert validate(m) is m
    again = validate(m.points, m.tets, source="arrays.vtu")
    assert again.source == "arrays.vtu"
    np.testing.assert_array_equal(again.tets, m.tets)


def test_unreferenced_points_dropped_and_nan_there_ignored() -> None:
    m = structured_box((1, 1, 1))
    points = np.concatenate([[[np.nan, 0.0, 0.0]], m.points])
    out = validate(points, m.tets + 1)
    np.testing.assert_array_equal(out.points, m.points)
    np.testing.assert_array_equal(out.tets, m.tets)
    keep = ValidationOptions(drop_unreferenced=False)
    with pytest.raises(InputError, match=r"point 0 \(used by no tet\) has a non-finite"):
        validate(points, m.tets + 1, options=keep)


def test_inverted_tet_fixed_with_warning_or_refused() -> None:
    m = structured_box((2, 1, 1))
    tets = m.tets.copy()
    tets[7, [0, 1]] = tets[7, [1, 0]]
    with pytest.warns(MeshWarning, match=r"re-oriented 1 inverted tets \(first: tet 7\)"):
        fixed = validate(m.points, tets, source="inv.vtu")
    assert fixed.volumes.min() > 0 and fixed.volume == pytest.approx(1.0, rel=1e-14)
    with pytest.raises(InputError, match=r"inv\.vtu: tet 7 is inverted"):
        validate(m.points, tets, source="inv.vtu", options=ValidationOptions(fix_orientation=False))


def test_degenerate_tet_names_index_and_volume() -> None:
    m = structured_box((1, 1, 1))
    flat = np.array([[2.0, 0, 0], [3, 0, 0], [2, 1, 0], [3, 1, 1e-9]])
    points = np.concatenate([m.points, flat])
    tets = np.concatenate([m.tets, [[8, 9, 10, 11]]])
    with pytest.raises(InputError, match=r"deg\.msh: tet 6 is degenerate: volume 1\.667e-10"):
        validate(points, tets, source="deg.msh")
    repeated = np.concatenate([m.tets, [[0, 1, 1, 2]]])
    with pytest.raises(InputError, match=r"tet 6 is degenerate: volume 0\.000e\+00"):
        validate(m.points, repeated)


def test_duplicate_tet_names_both_indices() -> None:
    m = structured_box((1, 1, 1))
    even_permutation = m.tets[2][[1, 2, 0, 3]]
    with pytest.raises(InputError, match=r"dup\.vtu: tets 2 and 6 are duplicates"):
        validate(m.points, np.concatenate([m.tets, [even_permutation]]), source="dup.vtu")


def test_face_in_three_tets_and_overlap_refused() -> None:
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1]])
    tets = np.array([[0, 1, 2, 3], [0, 2, 1, 4], [0, 1, 2, 5]])
    with pytest.raises(InputError, match=r"face \[0, 1, 2\] is shared by 3 tets \[0, 1, 2\]"):
        validate(points, tets)
    with pytest.raises(InputError, match=r"tets 0 and 1 overlap across face \[0, 1, 2\]"):
        validate(points, tets[[0, 2]])


def test_two_cubes_sharing_an_edge_refused() -> None:
    points, tets = two_cubes((1.0, 1.0, 0.0))
    shared = [int(np.flatnonzero((points == v).all(axis=1))[0]) for v in ([1, 1, 0], [1, 1, 1])]
    msg = re.escape(f"boundary edge {sorted(shared)} is in 4 boundary triangles")
    with pytest.raises(InputError, match=r"edge\.vtu: " + msg + r" \(tets \[0, 2, 10, 11\]\)"):
        validate(points, tets, source="edge.vtu")


def test_two_cubes_sharing_a_vertex_refused() -> None:
    points, tets = two_cubes((1.0, 1.0, 1.0))
    corner = int(np.flatnonzero((points == 1.0).all(axis=1))[0])
    with pytest.raises(InputError, match=rf"vert\.vtu: boundary vertex {corner} joins 2 "):
        validate(points, tets, source="vert.vtu")
    assert validate(points, tets, options=ValidationOptions(check_manifold=False)).n_tets == 12
    assert tet_components(tets)[0] == 2


def test_two_cubes_sharing_a_face_accepted() -> None:
    points, tets = two_cubes((1.0, 0.0, 0.0))
    m = validate(points, tets)
    assert m.n_points == 12 and m.n_components == 1
    assert divergence_volume(m.points, m.boundary) == pytest.approx(2.0, rel=1e-12)


@pytest.mark.parametrize(("points", "tets", "message"), [
    (np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64), r"empty mesh \(0 points, 0 tets\)"),
    (np.zeros((4, 2)), [[0, 1, 2, 3]], r"points must have shape \(n, 3\), got \(4, 2\)"),
    (np.eye(4, 3), [[0, 1, 2]], r"tets must have shape \(m, 4\), got \(1, 3\)"),
    (np.eye(4, 3), [[0.0, 1, 2, 3]], r"tets must be integer vertex indices, got dtype float64"),
    (np.eye(4, 3), [[0, 1, 2, 3], [0, 1, 2, -1]], r"tet 1 has a vertex index out of range"),
    (np.eye(4, 3), [[0, 1, 2, 4]], r"tet 0 has a vertex index out of range \[0, 4\)"),
    (np.eye(4, 3) * 1e9, [[0, 1, 2, 3]], r"point 0 \(used by tet 0\) has a coordinate beyond"),
    ([["a", "b", "c"]], [[0, 0, 0, 0]], r"points are not a numeric array"),
    (np.eye(4, 3) * 1j, [[0, 1, 2, 3]], r"points must be real"),
])
def test_garbage_arrays_raise_input_error(points: object, tets: object, message: str) -> None:
    with pytest.raises(InputError, match=message):
        validate(points, tets)


def test_nan_coordinate_names_point_and_tet() -> None:
    m = structured_box((1, 1, 1))
    points = m.points.copy()
    points[5, 1] = np.nan
    with pytest.raises(InputError, match=r"nan\.xdmf: point 5 \(used by tet 1\) has a non-finite"):
        validate(points, m.tets, source="nan.xdmf")


def test_options_validated() -> None:
    with pytest.raises(InputError, match="ValidationOptions.degenerate_tol"):
        ValidationOptions(degenerate_tol=-1.0)
    with pytest.raises(InputError, match="ValidationOptions.max_abs_coordinate"):
        ValidationOptions(max_abs_coordinate=float("inf"))
    with pytest.raises(InputError, match="ValidationOptions.degenerate_tol must be a float"):
        ValidationOptions(degenerate_tol="small")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="ValidationOptions.fix_orientation must be a bool"):
        ValidationOptions(fix_orientation=1)  # type: ignore[arg-type]


def test_tetmesh_arrays_are_read_only_copies() -> None:
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    m = TetMesh(points, np.array([[0, 1, 2, 3]], dtype=np.int32))
    assert m.tets.dtype == np.int64 and m.points.dtype == np.float64
    with pytest.raises(ValueError, match="read-only"):
        m.points[0, 0] = 1.0
    points[1, 0] = 5.0  # the caller's array stays writable and does not alias the mesh
    assert m.points[1, 0] == 1.0 and m.volume == pytest.approx(1.0 / 6.0, rel=1e-15)
    again = TetMesh(m.points, m.tets, "again")
    assert again.points is m.points and again.tets is m.tets  # no copy of frozen arrays


_garbage = st.one_of(
    hnp.arrays(st.sampled_from([np.float64, np.int64, np.int8, np.uint64, np.bool_]),
               hnp.array_shapes(min_dims=0, max_dims=3, max_side=6),
               elements=None),
    st.lists(st.one_of(st.integers(-5, 10), st.floats(allow_nan=True), st.text(max_size=2)),
             max_size=8),
    st.none(),
)


@settings(max_examples=300, deadline=None)
@given(points=st.one_of(_garbage, hnp.arrays(np.float64, st.tuples(st.integers(0, 8),
                                                                     st.just(3)))),
       tets=st.one_of(_garbage, hnp.arrays(np.int64, st.tuples(st.integers(0, 6), st.just(4)),
                                           elements=st.integers(-2, 9))))
def test_validate_raises_only_input_error(points: object, tets: object) -> None:
    try:
        out = validate(points, tets)
    except InputError:
        return
    assert out.volumes.min() > 0


def test_group_rows_matches_numpy_unique(rng: np.random.Generator) -> None:
    for high in (5, 2**40):  # packed int64 keys, and the np.unique(axis=0) fallback
        rows = rng.integers(0, high, size=(400, 3))
        rows[200:] = rows[rng.integers(0, 200, size=200)]
        first, inverse, counts = group_rows(rows)
        uniq, ref_inverse, ref_counts = np.unique(rows, axis=0, return_inverse=True,
                                                  return_counts=True)
        np.testing.assert_array_equal(rows[first], uniq)
        np.testing.assert_array_equal(inverse, ref_inverse.reshape(-1))
        np.testing.assert_array_equal(counts, ref_counts)
        np.testing.assert_array_equal(first, [np.flatnonzero(inverse == g)[0]
                                              for g in range(uniq.shape[0])])


def test_boundary_cells_own_their_faces() -> None:
    m = structured_box((2, 3, 1))
    faces, cells = boundary_faces_with_cells(m.tets)
    for f, c in zip(faces, cells, strict=True):
        assert set(f.tolist()) < set(m.tets[c].tolist())
    np.testing.assert_array_equal(faces, m.boundary)


def brute_force_closed_manifold(tets: np.ndarray) -> bool:
    """Reference: faces in <= 2 tets, boundary edges in 2 triangles, vertex links connected."""
    faces = Counter(frozenset(f) for t in tets.tolist() for f in combinations(t, 3))
    if max(faces.values()) > 2:
        return False
    boundary = [f for f, c in faces.items() if c == 1]
    edges = Counter(frozenset(e) for f in boundary for e in combinations(sorted(f), 2))
    if any(c != 2 for c in edges.values()):
        return False
    for v in set().union(*boundary):
        link = [tuple(f - {v}) for f in boundary if v in f]
        seen, todo = {link[0][0]}, [link[0][0]]
        while todo:
            u = todo.pop()
            for a, b in link:
                for x, y in ((a, b), (b, a)):
                    if x == u and y not in seen:
                        seen.add(y)
                        todo.append(y)
        if len(seen) != len(link):
            return False
    return True


def test_manifold_check_agrees_with_brute_force(rng: np.random.Generator) -> None:
    grid = structured_box((3, 3, 3))
    accepted = refused = 0
    for trial in range(160):
        if trial < 120:
            keep = np.repeat(rng.random(27) < 0.7, 6)
        else:
            keep = np.ones(grid.n_tets, dtype=bool)
            keep[rng.choice(grid.n_tets, size=rng.integers(1, 4), replace=False)] = False
        if not keep.any():
            continue
        tets = grid.tets[keep]
        expected = brute_force_closed_manifold(tets)
        try:
            m = validate(grid.points, tets)
        except InputError as err:
            assert not expected, str(err)
            assert re.match(r"<arrays>: (boundary (edge|vertex)|face) ", str(err)), str(err)
            refused += 1
            continue
        assert expected
        assert abs(divergence_volume(m.points, m.boundary) - m.volume) <= 1e-12
        accepted += 1
    print(f"accepted {accepted}, refused {refused}")
    assert accepted >= 10 and refused >= 10


def test_overrides_replace_option_fields() -> None:
    m = structured_box((1, 1, 1))
    tets = m.tets.copy()
    tets[0, [2, 3]] = tets[0, [3, 2]]
    with pytest.raises(InputError, match="tet 0 is inverted"):
        validate(m.points, tets, fix_orientation=False)
    with pytest.raises(InputError, match="ValidationOptions has no field 'fix_orientaton'"):
        validate(m.points, tets, fix_orientaton=False)
