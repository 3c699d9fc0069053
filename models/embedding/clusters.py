"""Cluster centres, the constraint matrix H and the disjoint partition (numpy/scipy/numba).

Remillard & Kry 2013 (section 4.3 of the draft) hold the shell to the body through c << n
clusters: cluster C with centre vertex c_C has weights
``alpha_i = w_C exp(-d_i^2 / (2 sigma^2))`` for ``d_i < 2 sigma`` (0 otherwise), ``d_i`` the
shortest path along mesh edges (Dijkstra, edge lengths as weights) from vertex i to the centre,
and ``w_C`` normalising the row to 1. The rows form ``H`` (``c x n``, acting on each coordinate):
the penalty ``||H (x - B v_q)||^2`` fixes the low frequencies and leaves wrinkles in the null
space of H. Supports overlap.

Centres are spread evenly by
  * farthest-point sampling (default, the author's code jiongchen/bigbang): the next centre is
    the vertex farthest (edge-path) from all chosen centres; stopping at a spacing ``r`` makes
    centres pairwise at least ``r`` apart and leaves every vertex within ``r`` of a centre;
  * greedy breadth-first growth (the draft / Remillard & Kry): the next centre is the vertex
    outside every centre's radius ``r`` that is closest to the covered region, so the covered
    region grows like a breadth-first front; the same two guarantees hold.

Sizing: an explicit count (FPS stops after ``count`` centres, ``r`` = the last selection
distance), an explicit spacing, or physics: a skin of thickness h on a soft body wrinkles with
wavelength ``lambda = 2 pi h (Ebar_f / (3 Ebar_s))^(1/3)``, ``Ebar = E / (1 - nu^2)``
(Remillard & Kry 2013, after Cerda & Mahadevan 2003), giving ``r = lambda / 2`` and
``sigma = lambda / pi``. Without an explicit sigma, ``sigma = 2 r / pi`` (the same ratio), so
``2 sigma = 1.27 r`` covers every vertex.

Cost: every edge-path distance comes from one numba Dijkstra kernel (binary heap on the CSR
edge graph) that only labels vertices whose new distance is within a limit and below their
current label, with scratch arrays allocated once per call and reset only where they were
touched. A Gaussian row therefore costs its support (ball of radius ``2 sigma``), and a new
centre of either placement method costs the region it captures (incremental farthest-point
sampling); the next centre is the root of a tournament tree, not a scan of all n vertices. With
c proportional to n (supports of bounded size) the set-up is O(n log n): farthest-point
sampling lowers a vertex's distance about ln c times. The results are those of full-length scipy
``csgraph.dijkstra`` passes: same centres, same distances, H to round-off (row sums added in
another order).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.sparse.linalg import eigsh

from meshes.errors import InputError
from models.embedding.subdivision import edge_topology

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
Method = Literal["fps", "bfs"]

_DENSE_SVD_LIMIT = 4_000_000  # c * n entries up to which the dense SVD of H is used


def _positive_or_none(name: str, value: float | int | None) -> None:
    """Raise InputError unless ``value`` is None or a finite positive number."""
    if value is not None and not (np.isfinite(value) and value > 0):
        raise InputError(f"ClusterOptions.{name}: expected a positive number, got {value!r}")


@dataclass(frozen=True)
class ClusterOptions:
    """How to place the clusters and size their Gaussian weights.

    Exactly one sizing is used: ``count``, else ``spacing``, else the skin physics
    (``skin_thickness`` with the moduli), else the default ``count = 200`` of the author's code.

    Attributes:
        method: "fps" (farthest-point sampling, default) or "bfs" (greedy breadth-first growth).
        count: number of clusters (FPS; for "bfs" the spacing is estimated from the surface
            area, ``r = sqrt(2 A / (sqrt(3) count))`` of a hexagonal packing, so the count is
            approximate).
        spacing: minimal edge-path distance between centres r (length unit).
        sigma: Gaussian width (length unit); None for ``2 r / pi``.
        skin_thickness: skin thickness h (length unit) for the physical sizing.
        skin_E: Young's modulus of the skin E_f (Pa).
        skin_nu: Poisson ratio of the skin nu_f.
        body_E: Young's modulus of the soft body E_s (Pa).
        body_nu: Poisson ratio of the body nu_s.
        seed_vertex: index of the first centre.

    """

    method: Method = "fps"
    count: int | None = None
    spacing: float | None = None
    sigma: float | None = None
    skin_thickness: float | None = None
    skin_E: float = 1.0e6
    skin_nu: float = 0.3
    body_E: float = 1.0e4
    body_nu: float = 0.45
    seed_vertex: int = 0

    def __post_init__(self) -> None:
        if self.method not in ("fps", "bfs"):
            raise InputError(f"ClusterOptions.method: expected 'fps' or 'bfs', "
                             f"got {self.method!r}")
        if self.count is not None and (not isinstance(self.count, int) or self.count < 1):
            raise InputError(f"ClusterOptions.count: expected an integer >= 1, "
                             f"got {self.count!r}")
        for name in ("spacing", "sigma", "skin_thickness", "skin_E", "body_E"):
            _positive_or_none(name, getattr(self, name))
        for name in ("skin_nu", "body_nu"):
            if not -1.0 < getattr(self, name) < 1.0:
                raise InputError(f"ClusterOptions.{name}: expected -1 < nu < 1, "
                                 f"got {getattr(self, name)!r}")
        if not isinstance(self.seed_vertex, int) or self.seed_vertex < 0:
            raise InputError(f"ClusterOptions.seed_vertex: expected an integer >= 0, "
                             f"got {self.seed_vertex!r}")


@dataclass(frozen=True)
class ClusterReport:
    """Statistics of the clusters.

    Attributes:
        count: number of clusters c.
        spacing: centre spacing r used (length unit).
        sigma: Gaussian width used (length unit).
        mean_support: mean number of vertices with nonzero weight per cluster.
        min_support: smallest support.
        max_support: largest support.
        uncovered: vertices with no nonzero weight in any cluster.
        min_singular_value: smallest singular value of H (> 0: full row rank).

    """

    count: int
    spacing: float
    sigma: float
    mean_support: float
    min_support: int
    max_support: int
    uncovered: int
    min_singular_value: float


@dataclass(frozen=True)
class Clusters:
    """Clusters on a shell.

    Attributes:
        H: ``(c, n)`` CSR constraint matrix, rows sum to 1, acting on each coordinate.
        centres: ``(c,)`` centre vertex of each cluster.
        partition: ``(n,)`` cluster id of the nearest centre (edge-path) of each vertex.
        report: the statistics.

    """

    H: sp.csr_matrix
    centres: IntArray
    partition: IntArray
    report: ClusterReport


def effective_modulus(E: float, nu: float) -> float:
    """Plane-strain modulus ``Ebar = E / (1 - nu^2)``."""
    return E / (1.0 - nu * nu)


def wrinkle_wavelength(h: float, E_f: float, nu_f: float, E_s: float, nu_s: float) -> float:
    """Wrinkle wavelength of a stiff skin on a soft substrate.

    ``lambda = 2 pi h (Ebar_f / (3 Ebar_s))^(1/3)`` (Remillard & Kry 2013, eq. for cluster
    sizing; Cerda & Mahadevan 2003).

    Args:
        h: skin thickness.
        E_f: skin Young's modulus.
        nu_f: skin Poisson ratio.
        E_s: substrate Young's modulus.
        nu_s: substrate Poisson ratio.

    Returns:
        The wavelength lambda (unit of h).

    """
    ratio = effective_modulus(E_f, nu_f) / (3.0 * effective_modulus(E_s, nu_s))
    return 2.0 * np.pi * h * ratio ** (1.0 / 3.0)


def edge_graph(vertices: FloatArray, faces: IntArray) -> sp.csr_matrix:
    """Symmetric ``n x n`` graph of the mesh edges weighted by their lengths.

    Zero-length edges get a tiny positive weight (scipy drops explicit zeros).

    Args:
        vertices: ``(n, 3)`` positions.
        faces: ``(m, 3)`` faces.

    Returns:
        The CSR adjacency with edge lengths.

    """
    n = vertices.shape[0]
    e = edge_topology(faces, n).edges
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    w = np.maximum(w, 1e-12 * max(float(w.mean()) if w.size else 0.0, 1e-300))
    g = sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(n, n))
    return g.tocsr()


# --- numba kernels: binary heap, truncated / pruned Dijkstra --------------------------------


@numba.njit(cache=True, inline="always")
def _before(key_a: float, item_a: int, key_b: float,
            item_b: int) -> bool:  # pragma: no cover - numba
    """Heap order: smaller key first, ties by smaller item (vertex index)."""
    return key_a < key_b or (key_a == key_b and item_a < item_b)


@numba.njit(cache=True)
def _sift_down(keys: FloatArray, items: IntArray, size: int,
               i: int) -> None:  # pragma: no cover - numba
    """Move entry ``i`` of the binary min-heap ``keys[:size], items[:size]`` down into place."""
    key, item = keys[i], items[i]
    while True:
        child = 2 * i + 1
        if child >= size:
            break
        if child + 1 < size and _before(keys[child + 1], items[child + 1], keys[child],
                                        items[child]):
            child += 1
        if not _before(keys[child], items[child], key, item):
            break
        keys[i], items[i] = keys[child], items[child]
        i = child
    keys[i], items[i] = key, item


@numba.njit(cache=True)
def _heap_push(keys: FloatArray, items: IntArray, size: int, key: float,
               item: int) -> int:  # pragma: no cover - numba
    """Insert ``(key, item)`` into the min-heap of ``size`` entries; the new size."""
    i = size
    while i > 0:
        parent = (i - 1) >> 1
        if not _before(key, item, keys[parent], items[parent]):
            break
        keys[i], items[i] = keys[parent], items[parent]
        i = parent
    keys[i], items[i] = key, item
    return size + 1


@numba.njit(cache=True)
def _heap_pop(keys: FloatArray, items: IntArray, size: int) -> int:  # pragma: no cover - numba
    """Remove the root (smallest entry) of the min-heap of ``size >= 1`` entries; new size."""
    size -= 1
    if size > 0:
        keys[0], items[0] = keys[size], items[size]
        _sift_down(keys, items, size, 0)
    return size


@numba.njit(cache=True)
def _dijkstra_update(indptr: IntArray, indices: IntArray, weights: FloatArray, source: int,
                     limit: float, dist: FloatArray, heap_keys: FloatArray, heap_items: IntArray,
                     settled: IntArray) -> int:  # pragma: no cover - numba
    """Dijkstra from ``source`` lowering the labels ``dist`` in place.

    A vertex gets the path length ``d`` only if ``d <= limit`` (as scipy's ``limit``) and
    ``d < dist[u]``, and the search does not continue through the others. With ``dist = inf``
    this is the Dijkstra truncated at ``limit``; with ``dist`` = the current distance to the
    nearest centre it is the incremental update by a new centre: the labels become
    ``min(dist, d_source)`` exactly (a vertex that keeps its label has a neighbourhood that
    cannot be improved through it). The work is proportional to the lowered vertices and
    their edges, never to n.

    Args:
        indptr: ``(n + 1,)`` CSR row pointers of the edge graph.
        indices: ``(nnz,)`` CSR neighbours.
        weights: ``(nnz,)`` positive edge lengths.
        source: start vertex.
        limit: largest path length labelled.
        dist: ``(n,)`` labels, lowered in place.
        heap_keys: ``(nnz + 1,)`` scratch.
        heap_items: ``(nnz + 1,)`` scratch.
        settled: ``(n,)`` output: the lowered vertices, each once, in order of distance.

    Returns:
        The number k of lowered vertices, ``settled[:k]``.

    """
    if not (0.0 <= limit and 0.0 < dist[source]):
        return 0
    dist[source] = 0.0
    size = _heap_push(heap_keys, heap_items, 0, 0.0, source)
    count = 0
    while size > 0:
        d, v = heap_keys[0], heap_items[0]
        size = _heap_pop(heap_keys, heap_items, size)
        if d > dist[v]:  # stale entry: v was pushed again with a smaller distance
            continue
        settled[count] = v
        count += 1
        for j in range(indptr[v], indptr[v + 1]):
            u = indices[j]
            du = d + weights[j]
            if du <= limit and du < dist[u]:
                dist[u] = du
                size = _heap_push(heap_keys, heap_items, size, du, u)
    return count


@numba.njit(cache=True, inline="always")
def _winner(tree: IntArray, i: int, mind: FloatArray,
            sign: float) -> int:  # pragma: no cover - numba
    """Winner of node ``i`` from its two children: smaller ``sign * mind``, ties to the left.

    The left subtree holds the smaller vertex ids, so ties go to the first vertex (as
    ``np.argmax`` / ``np.argmin``); -1 marks a subtree without candidates.
    """
    a, b = tree[2 * i], tree[2 * i + 1]
    if a < 0:
        return b
    if b < 0 or sign * mind[a] <= sign * mind[b]:
        return a
    return b


@numba.njit(cache=True)
def _tree_build(mind: FloatArray, sign: float, floor: float) -> IntArray:  # pragma: no cover
    """Tournament tree over the vertices with ``mind >= floor`` (candidates).

    ``tree[1]`` is the candidate of smallest ``sign * mind`` (first on ties), -1 if none;
    leaf ``v`` is ``tree[leaves + v]`` with ``leaves`` the power of two ``>= n``.
    """
    n = mind.size
    leaves = 1
    while leaves < n:
        leaves *= 2
    tree = np.full(2 * leaves, -1, dtype=np.int64)
    for v in range(n):
        if mind[v] >= floor:
            tree[leaves + v] = v
    for i in range(leaves - 1, 0, -1):
        tree[i] = _winner(tree, i, mind, sign)
    return tree


@numba.njit(cache=True)
def _tree_update(tree: IntArray, v: int, mind: FloatArray, sign: float,
                 floor: float) -> None:  # pragma: no cover - numba
    """Refresh the tournament tree after ``mind[v]`` decreased.

    Walks up from leaf ``v`` and stops at the first node whose winner is unchanged and is not
    ``v`` itself (its value, hence every ancestor, is then unchanged): O(1) for most vertices.
    """
    i = tree.size // 2 + v
    tree[i] = v if mind[v] >= floor else -1
    i //= 2
    while i >= 1:
        w = _winner(tree, i, mind, sign)
        if w == tree[i] and w != v:
            return
        tree[i] = w
        i //= 2


@numba.njit(cache=True)
def _select_centres(indptr: IntArray, indices: IntArray, weights: FloatArray, seed: int,
                    max_count: int, spacing: float, farthest: bool,
                    mind: FloatArray) -> tuple[IntArray, float]:  # pragma: no cover - numba
    """Farthest-point sampling or greedy breadth-first growth with incremental distances.

    ``mind`` (in place, ``inf`` on entry) is the edge-path distance to the nearest centre.
    Farthest (FPS): the next centre is the first vertex of largest ``mind`` (``np.argmax``),
    taken while ``mind >= spacing`` and ``> 0``; the distances are not truncated. Otherwise
    (BFS): the next centre is the first vertex of smallest ``mind >= spacing`` (unreached:
    ``inf``) and every distance is truncated at ``2 spacing``. The selection is the root of a
    tournament tree refreshed at the vertices each new centre brought closer.

    Args:
        indptr: CSR row pointers of the edge graph.
        indices: CSR neighbours.
        weights: edge lengths.
        seed: first centre.
        max_count: stop after this many centres.
        spacing: FPS: stop below this distance (0: no limit); BFS: the radius r.
        farthest: FPS if True, else BFS.
        mind: ``(n,)`` distances to the nearest centre, filled in place.

    Returns:
        ``(centres, r)``: the centres in order and the last FPS selection distance
        (``inf`` if none was selected after the seed; unused for BFS).

    """
    n = mind.size
    limit = np.inf if farthest else 2.0 * spacing
    sign = -1.0 if farthest else 1.0
    floor = -np.inf if farthest else spacing
    heap_keys = np.empty(indices.size + 1)
    heap_items = np.empty(indices.size + 1, dtype=np.int64)
    settled = np.empty(n, dtype=np.int64)
    centres = np.empty(max(max_count, 1), dtype=np.int64)
    centres[0] = seed
    count, r = 1, np.inf
    _dijkstra_update(indptr, indices, weights, seed, limit, mind, heap_keys, heap_items,
                     settled)
    tree = _tree_build(mind, sign, floor)
    while count < max_count and tree[1] >= 0:
        nxt = tree[1]
        if farthest:
            if mind[nxt] < spacing or mind[nxt] == 0.0:
                break
            r = mind[nxt]
        centres[count] = nxt
        count += 1
        k = _dijkstra_update(indptr, indices, weights, nxt, limit, mind, heap_keys, heap_items,
                             settled)
        for i in range(k):
            _tree_update(tree, settled[i], mind, sign, floor)
    return centres[:count].copy(), r


@numba.njit(cache=True)
def _balls(indptr: IntArray, indices: IntArray, weights: FloatArray, centres: IntArray,
           radius: float) -> tuple[IntArray, IntArray, FloatArray]:  # pragma: no cover - numba
    """Vertices at edge-path distance ``< radius`` of each centre, as CSR rows.

    Args:
        indptr: CSR row pointers of the edge graph.
        indices: CSR neighbours.
        weights: edge lengths.
        centres: ``(c,)`` centre vertices.
        radius: ball radius (exclusive).

    Returns:
        ``(rowptr, columns, distances)``: row ``C`` holds the ball of centre ``C`` in
        ascending vertex order, ``columns[rowptr[C]:rowptr[C + 1]]``.

    """
    n = indptr.size - 1
    dist = np.full(n, np.inf)
    heap_keys = np.empty(indices.size + 1)
    heap_items = np.empty(indices.size + 1, dtype=np.int64)
    settled = np.empty(n, dtype=np.int64)
    rowptr = np.zeros(centres.size + 1, dtype=np.int64)
    columns = np.empty(max(16, 4 * n), dtype=np.int64)
    distances = np.empty(columns.size)
    nnz = 0
    for c in range(centres.size):
        k = _dijkstra_update(indptr, indices, weights, centres[c], radius, dist, heap_keys,
                             heap_items, settled)
        if nnz + k > columns.size:
            grown = max(2 * columns.size, nnz + k)
            columns = np.concatenate((columns, np.empty(grown - columns.size, np.int64)))
            distances = np.concatenate((distances, np.empty(grown - distances.size)))
        for v in np.sort(settled[:k]):
            if dist[v] < radius:
                columns[nnz], distances[nnz] = v, dist[v]
                nnz += 1
        for i in range(k):  # reset only what this ball touched
            dist[settled[i]] = np.inf
        rowptr[c + 1] = nnz
    return rowptr, columns[:nnz].copy(), distances[:nnz].copy()


def _csr_arrays(graph: sp.csr_matrix) -> tuple[IntArray, IntArray, FloatArray]:
    """``(indptr, indices, data)`` of the edge graph as int64 / float64 arrays."""
    g = sp.csr_matrix(graph)
    return (np.asarray(g.indptr, dtype=np.int64), np.asarray(g.indices, dtype=np.int64),
            np.asarray(g.data, dtype=np.float64))


def _check_vertices(name: str, ids: IntArray, n: int) -> None:
    """Raise InputError unless every vertex id is in ``[0, n)`` (numba does not check)."""
    if ids.size and (ids.min() < 0 or ids.max() >= n):
        raise InputError(f"{name}: vertex ids must be in [0, {n}), got "
                         f"[{ids.min()}, {ids.max()}]")


def farthest_point_centres(graph: sp.csr_matrix, seed: int, count: int | None,
                           spacing: float | None) -> tuple[IntArray, float]:
    """Farthest-point sampling with edge-path distance.

    Incremental: a new centre's Dijkstra only visits the vertices it brings closer.

    Args:
        graph: edge-length graph.
        seed: first centre.
        count: stop after this many centres (None: no limit).
        spacing: stop when the farthest vertex is closer than this (None: no limit).

    Returns:
        ``(centres, r)``: the centres and the last selection distance (min pairwise distance
        of the centres, >= ``spacing``; also a bound on every vertex's distance to a centre).

    Raises:
        InputError: ``seed`` is not a vertex.

    """
    n = graph.shape[0]
    _check_vertices("farthest_point_centres: seed", np.array([seed], dtype=np.int64), n)
    mind = np.full(n, np.inf)
    limit = n if count is None else min(count, n)
    centres, r = _select_centres(*_csr_arrays(graph), int(seed), int(limit),
                                 0.0 if spacing is None else float(spacing), True, mind)
    if spacing is not None:
        r = spacing
    elif not np.isfinite(r):
        r = float(mind[np.isfinite(mind)].max())
    return centres, float(r)


def greedy_bfs_centres(graph: sp.csr_matrix, seed: int, spacing: float) -> IntArray:
    """Greedy breadth-first growth (Remillard & Kry 2013): centres >= ``spacing`` apart.

    The next centre is the uncovered vertex (distance >= spacing to every centre) closest to
    the covered region; unreached components start at their lowest vertex index. Distances
    are truncated at ``2 spacing`` and updated incrementally per new centre.

    Args:
        graph: edge-length graph.
        seed: first centre.
        spacing: radius r of a cluster's region.

    Returns:
        The centres in order of growth.

    Raises:
        InputError: ``seed`` is not a vertex.

    """
    n = graph.shape[0]
    _check_vertices("greedy_bfs_centres: seed", np.array([seed], dtype=np.int64), n)
    centres, _ = _select_centres(*_csr_arrays(graph), int(seed), n, float(spacing), False,
                                 np.full(n, np.inf))
    return centres


def surface_area(vertices: FloatArray, faces: IntArray) -> float:
    """Total area of a triangle mesh."""
    a, b, c = (vertices[faces[:, j]] for j in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def gaussian_weights(graph: sp.csr_matrix, centres: IntArray, sigma: float) -> sp.csr_matrix:
    """``H`` with ``alpha_i ~ exp(-d_i^2 / (2 sigma^2))`` for ``d_i < 2 sigma``, rows sum to 1.

    One Dijkstra truncated at ``2 sigma`` per centre, costing its support only.

    Args:
        graph: edge-length graph.
        centres: ``(c,)`` centre vertices.
        sigma: Gaussian width.

    Returns:
        ``(c, n)`` CSR matrix (sorted column indices).

    Raises:
        InputError: a centre is not a vertex, or ``sigma`` is not a positive number.

    """
    n = graph.shape[0]
    c = np.asarray(centres, dtype=np.int64)
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"gaussian_weights: sigma must be a positive number, got {sigma!r}")
    _check_vertices("gaussian_weights: centres", c, n)
    rowptr, columns, d = _balls(*_csr_arrays(graph), c, 2.0 * sigma)
    w = np.exp(-0.5 * (d / sigma) ** 2)
    rows = np.repeat(np.arange(c.size), np.diff(rowptr))
    w /= np.bincount(rows, weights=w, minlength=c.size)[rows]
    return sp.csr_matrix((w, columns, rowptr), shape=(c.size, n))


def nearest_centre_partition(graph: sp.csr_matrix, centres: IntArray) -> IntArray:
    """Cluster id of the edge-path nearest centre of every vertex (-1 if unreachable)."""
    _, _, sources = csgraph.dijkstra(graph, indices=centres, min_only=True,
                                     return_predecessors=True)
    lookup = np.full(graph.shape[0], -1, dtype=np.int64)
    lookup[centres] = np.arange(centres.size)
    return np.where(sources >= 0, lookup[np.maximum(sources, 0)], -1)


def smallest_singular_value(H: sp.csr_matrix) -> float:
    """Smallest singular value of ``H`` (``c <= n``).

    Dense SVD when ``c n`` is small; otherwise ``sqrt(lambda_min(H H^T))`` by Lanczos
    (``eigsh`` shift-invert just below 0 on the sparse ``c x c`` Gram matrix), accurate to
    about ``sqrt(eps) sigma_max`` in absolute terms (the Gram matrix squares the condition).

    Args:
        H: the ``(c, n)`` matrix.

    Returns:
        ``sigma_min``.

    """
    if H.shape[0] * H.shape[1] <= _DENSE_SVD_LIMIT:
        return float(np.linalg.svd(H.toarray(), compute_uv=False).min())
    gram = (H @ H.T).tocsc()
    shift = -1e-10 * float(gram.diagonal().max())  # G - shift I is SPD even if G is singular
    lam = eigsh(gram, k=1, sigma=shift, which="LM", return_eigenvectors=False)
    return float(np.sqrt(max(float(lam[0]), 0.0)))


def cluster_sizing(opts: ClusterOptions, vertices: FloatArray, faces: IntArray
            ) -> tuple[int | None, float | None, float | None]:
    """Return ``(count, spacing, sigma)`` from the options (physics, explicit or default)."""
    if opts.count is not None:
        if opts.method == "bfs":
            r = np.sqrt(2.0 * surface_area(vertices, faces) / (np.sqrt(3.0) * opts.count))
            return None, float(r), opts.sigma
        return opts.count, None, opts.sigma
    if opts.spacing is not None:
        return None, opts.spacing, opts.sigma
    if opts.skin_thickness is not None:
        lam = wrinkle_wavelength(opts.skin_thickness, opts.skin_E, opts.skin_nu, opts.body_E,
                                 opts.body_nu)
        return None, lam / 2.0, opts.sigma if opts.sigma is not None else lam / np.pi
    return cluster_sizing(ClusterOptions(method=opts.method, count=200, sigma=opts.sigma),
                   vertices, faces)


def build_clusters(vertices: FloatArray, faces: IntArray,
                   options: ClusterOptions | None = None) -> Clusters:
    """Place cluster centres on the shell and build H and the partition.

    Args:
        vertices: ``(n, 3)`` rest positions of the shell.
        faces: ``(m, 3)`` shell faces.
        options: placement and sizing.

    Returns:
        The ``Clusters``.

    Raises:
        InputError: bad arrays or ``seed_vertex`` out of range.

    """
    opts = options or ClusterOptions()
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"vertices/faces: expected (n, 3) and (m, 3), got {v.shape}, {f.shape}")
    if opts.seed_vertex >= v.shape[0]:
        raise InputError(f"ClusterOptions.seed_vertex: {opts.seed_vertex} >= vertex count "
                         f"{v.shape[0]}")
    graph = edge_graph(v, f)
    count, spacing, sigma = cluster_sizing(opts, v, f)
    if opts.method == "bfs" and spacing is not None:
        centres, r = greedy_bfs_centres(graph, opts.seed_vertex, spacing), spacing
    else:
        centres, r = farthest_point_centres(graph, opts.seed_vertex, count, spacing)
    sigma = sigma if sigma is not None else 2.0 * r / np.pi
    H = gaussian_weights(graph, centres, sigma)
    return Clusters(H=H, centres=centres, partition=nearest_centre_partition(graph, centres),
                    report=_report(H, r, sigma))


def _report(H: sp.csr_matrix, spacing: float, sigma: float) -> ClusterReport:
    """Support statistics and the smallest singular value of H."""
    support = np.diff(H.indptr)
    covered = np.zeros(H.shape[1], dtype=bool)
    covered[H.indices] = True
    return ClusterReport(count=int(H.shape[0]), spacing=float(spacing), sigma=float(sigma),
                         mean_support=float(support.mean()), min_support=int(support.min()),
                         max_support=int(support.max()),
                         uncovered=int(np.count_nonzero(~covered)),
                         min_singular_value=smallest_singular_value(H))
