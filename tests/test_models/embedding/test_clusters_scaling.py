"""Linear-cost cluster set-up (numba truncated / incremental Dijkstra) against the scipy one.

The reference functions below are the previous implementation of
:mod:`models.embedding.clusters` (one full-length ``csgraph.dijkstra`` per centre, dense
``(batch, n)`` distance blocks for H): the new code must give the same centres, the same
spacing r and the same H up to round-off (only the row sums are added in another order).
Speed is measured in ``benchmarks/cluster_setup.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse import csgraph

from meshes.errors import InputError
from meshes.shells import equilateral_plate, grid_plate, icosphere, irregular_plate
from models.embedding import clusters as cl
from models.embedding.clusters import (
    ClusterOptions,
    build_clusters,
    edge_graph,
    farthest_point_centres,
    gaussian_weights,
    greedy_bfs_centres,
    nearest_centre_partition,
)

H_ATOL = 1e-14  # H entries are in [0, 1]; only the order of the row sums differs

# --- reference: the scipy csgraph implementation before the numba kernels -------------------

REF_BATCH_ENTRIES = 20_000_000


def ref_distances(graph, source, limit):
    return csgraph.dijkstra(graph, indices=source, limit=limit)


def ref_farthest_point_centres(graph, seed, count, spacing):
    n = graph.shape[0]
    centres, r = [seed], np.inf
    mind = ref_distances(graph, seed, np.inf)
    limit = n if count is None else min(count, n)
    while len(centres) < limit:
        nxt = int(np.argmax(mind))
        if (spacing is not None and mind[nxt] < spacing) or mind[nxt] == 0.0:
            break
        r = float(mind[nxt])
        centres.append(nxt)
        mind = np.minimum(mind, ref_distances(graph, nxt, r))
    if spacing is not None:
        r = spacing
    elif not np.isfinite(r):
        r = float(mind[np.isfinite(mind)].max())
    return np.asarray(centres, dtype=np.int64), r


def ref_greedy_bfs_centres(graph, seed, spacing):
    centres = [seed]
    mind = ref_distances(graph, seed, 2.0 * spacing)
    while True:
        free = np.flatnonzero(mind >= spacing)
        if free.size == 0:
            return np.asarray(centres, dtype=np.int64)
        nxt = int(free[np.argmin(mind[free])])
        centres.append(nxt)
        mind = np.minimum(mind, ref_distances(graph, nxt, 2.0 * spacing))


def ref_gaussian_weights(graph, centres, sigma, batch_entries=REF_BATCH_ENTRIES):
    n = graph.shape[0]
    batch = max(1, batch_entries // max(n, 1))
    blocks = []
    for start in range(0, centres.size, batch):
        d = csgraph.dijkstra(graph, indices=centres[start:start + batch], limit=2.0 * sigma)
        w = np.where(d < 2.0 * sigma, np.exp(-0.5 * (np.minimum(d, 2.0 * sigma) / sigma) ** 2),
                     0.0)
        blocks.append(sp.csr_matrix(w / w.sum(axis=1, keepdims=True)))
    return sp.vstack(blocks, format="csr")


# --- meshes ---------------------------------------------------------------------------------


def two_plates_and_a_point():
    """Two disjoint equilateral plates plus one isolated vertex (three components)."""
    v, f = equilateral_plate(12, 10)
    v2 = np.vstack([v, v + [100.0, 0.0, 0.0], [[50.0, 50.0, 0.0]]])
    return v2, np.vstack([f, f + v.shape[0]])


MESHES = {
    "icosphere": lambda: icosphere(4),  # 2562 vertices, scattered numbering
    "irregular": lambda: irregular_plate(3000, seed=3),
    "grid_ties": lambda: grid_plate(40, 30, 4.0, 3.0, "right"),  # many equal distances
    "disconnected": two_plates_and_a_point,
}


@pytest.fixture(scope="module", params=list(MESHES))
def mesh(request):
    v, f = MESHES[request.param]()
    return request.param, v, f, edge_graph(v, f)


def assert_same_h(new, ref):
    """Same sparsity pattern (sorted columns) and entries to round-off."""
    ref = ref.tocsr()
    ref.sort_indices()
    assert new.shape == ref.shape
    np.testing.assert_array_equal(new.indptr, ref.indptr)
    np.testing.assert_array_equal(new.indices, ref.indices)
    diff = float(np.abs(new.data - ref.data).max())
    assert diff < H_ATOL
    np.testing.assert_allclose(np.asarray(new.sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-14)
    return diff


# --- the kernel -----------------------------------------------------------------------------


def test_truncated_dijkstra_is_scipy_limit(mesh):
    """Labels within ``limit`` bitwise equal to scipy's, the rest untouched, scratch reset."""
    name, v, f, g = mesh
    ip, ix, w = cl._csr_arrays(g)
    n = g.shape[0]
    dist = np.full(n, np.inf)
    keys, items = np.empty(ix.size + 1), np.empty(ix.size + 1, dtype=np.int64)
    settled = np.empty(n, dtype=np.int64)
    limit = 6.0 * float(w.mean())
    for source in (0, n // 3, n - 1):
        k = cl._dijkstra_update(ip, ix, w, source, limit, dist, keys, items, settled)
        ref = csgraph.dijkstra(g, indices=source, limit=limit)
        ball = np.flatnonzero(np.isfinite(ref))
        np.testing.assert_array_equal(np.sort(settled[:k]), ball)
        np.testing.assert_array_equal(dist[ball], ref[ball])  # bitwise
        assert np.all(np.diff(dist[settled[:k]]) >= 0)  # settled in order of distance
        assert np.isinf(np.delete(dist, ball)).all()
        dist[settled[:k]] = np.inf  # the reset gaussian_weights does
        print(name, source, "ball", k, "of", n)


def test_pruned_update_is_minimum(mesh):
    """With the current nearest-centre distances as labels: ``min(mind, d_new)`` exactly."""
    name, v, f, g = mesh
    ip, ix, w = cl._csr_arrays(g)
    n = g.shape[0]
    keys, items = np.empty(ix.size + 1), np.empty(ix.size + 1, dtype=np.int64)
    settled = np.empty(n, dtype=np.int64)
    mind = csgraph.dijkstra(g, indices=0)
    for source in (n // 2, n - 1, n // 5):
        expected = np.minimum(mind, csgraph.dijkstra(g, indices=source))
        lowered = expected < mind
        k = cl._dijkstra_update(ip, ix, w, source, np.inf, mind, keys, items, settled)
        np.testing.assert_array_equal(np.sort(settled[:k]), np.flatnonzero(lowered))
        np.testing.assert_array_equal(mind, expected)
        print(name, source, "lowered", k, "of", n)


# --- the public functions against the reference ---------------------------------------------


@pytest.mark.parametrize("sizing", [{"count": 40}, {"count": 1}, {"spacing": "r"}])
def test_farthest_point_centres_match(mesh, sizing):
    name, v, f, g = mesh
    count, spacing = sizing.get("count"), None
    if sizing.get("spacing") == "r":  # the spacing FPS reaches with 25 centres
        spacing = ref_farthest_point_centres(g, 0, 25, None)[1]
    ref_c, ref_r = ref_farthest_point_centres(g, 0, count, spacing)
    new_c, new_r = farthest_point_centres(g, 0, count, spacing)
    np.testing.assert_array_equal(new_c, ref_c)
    assert new_r == ref_r
    print(name, sizing, "centres", new_c.size, "r", new_r)


def test_farthest_point_all_vertices():
    """Without count or spacing FPS takes every vertex (down to r = min edge length)."""
    v, f = two_plates_and_a_point()
    g = edge_graph(v, f)
    ref_c, ref_r = ref_farthest_point_centres(g, 5, None, None)
    new_c, new_r = farthest_point_centres(g, 5, None, None)
    assert new_c.size == v.shape[0]
    np.testing.assert_array_equal(new_c, ref_c)
    assert new_r == ref_r


@pytest.mark.parametrize("scale", [1.0, 0.35])
def test_greedy_bfs_centres_match(mesh, scale):
    name, v, f, g = mesh
    spacing = scale * ref_farthest_point_centres(g, 0, 30, None)[1]
    ref = ref_greedy_bfs_centres(g, 0, spacing)
    new = greedy_bfs_centres(g, 0, spacing)
    np.testing.assert_array_equal(new, ref)
    print(name, "bfs spacing", spacing, "centres", new.size)


@pytest.mark.parametrize("scale", [1.0, 0.3, 3.0])
def test_gaussian_weights_match(mesh, scale):
    """Default sigma = 2 r / pi (covers all), a small sigma (uncovered vertices), a large one."""
    name, v, f, g = mesh
    centres, r = ref_farthest_point_centres(g, 0, 40, None)
    sigma = scale * 2.0 * r / np.pi
    ref = ref_gaussian_weights(g, centres, sigma)
    new = gaussian_weights(g, centres, sigma)
    diff = assert_same_h(new, ref)
    uncovered = int(np.count_nonzero(np.diff(ref.tocsc().indptr) == 0))
    if scale == 0.3:
        assert uncovered > 0  # some vertices are beyond every ball
    print(name, "sigma", sigma, "nnz", new.nnz, "uncovered", uncovered, "max |dH|", diff)


def test_gaussian_weights_several_reference_batches():
    """The reference in several dense batches and the new rows agree as well."""
    v, f = irregular_plate(2000, seed=1)
    g = edge_graph(v, f)
    centres, r = ref_farthest_point_centres(g, 7, 60, None)
    ref = ref_gaussian_weights(g, centres, 2.0 * r / np.pi, batch_entries=7 * g.shape[0])
    assert_same_h(gaussian_weights(g, centres, 2.0 * r / np.pi), ref)


@pytest.mark.parametrize("method", ["fps", "bfs"])
def test_build_clusters_matches_reference_pipeline(mesh, method):
    name, v, f, g = mesh
    c = build_clusters(v, f, ClusterOptions(method=method, count=30, seed_vertex=3))
    count, spacing, sigma = cl.cluster_sizing(ClusterOptions(method=method, count=30), v, f)
    if method == "bfs":
        centres, r = ref_greedy_bfs_centres(g, 3, spacing), spacing
    else:
        centres, r = ref_farthest_point_centres(g, 3, count, spacing)
    np.testing.assert_array_equal(c.centres, centres)
    assert c.report.spacing == r
    assert c.report.sigma == 2.0 * r / np.pi
    assert_same_h(c.H, ref_gaussian_weights(g, centres, 2.0 * r / np.pi))
    np.testing.assert_array_equal(c.partition, nearest_centre_partition(g, centres))


def test_out_of_range_vertices_raise():
    v, f = icosphere(1)
    g = edge_graph(v, f)
    with pytest.raises(InputError, match="gaussian_weights: centres"):
        gaussian_weights(g, np.array([0, v.shape[0]]), 0.5)
    with pytest.raises(InputError, match="farthest_point_centres: seed"):
        farthest_point_centres(g, -1, 3, None)
    with pytest.raises(InputError, match="greedy_bfs_centres: seed"):
        greedy_bfs_centres(g, v.shape[0], 0.5)
    with pytest.raises(InputError, match="gaussian_weights: sigma"):
        gaussian_weights(g, np.array([0]), 0.0)
