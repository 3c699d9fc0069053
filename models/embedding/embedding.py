"""The embedding matrix B: shell points as combinations of the coarse body's degrees of freedom.

For a shell point ``p`` inside coarse cell ``K`` with affine map ``x = x_0 + J X`` (P1
geometry), the weights are the coarse basis functions at ``p``:
``B[p, dof_j(K)] = phi_j(X)``, ``X = J^{-1} (p - x_0)``, tabulated by basix on the reference
tetrahedron (barycentric coordinates for P1, quadratic Lagrange values for P2). Columns are
dof *blocks* (one per node of the function space, not geometry nodes: the dolfinx dofmap is
used, never the geometry numbering), so ``B`` acts per scalar component:
``Y = B @ U`` with ``U = u.x.array.reshape(-1, bs)`` gives the ``(n, bs)`` shell values, and
for a vector space with ``bs = 3`` the rest shell is ``B @ V.tabulate_dof_coordinates()``.
Since the Lagrange basis is a partition of unity that reproduces polynomials up to its degree,
rows sum to 1 and linear (P1, P2) and quadratic (P2) fields are reproduced exactly
(Remillard & Kry 2013, section 4.1; Vega FEM and SOFA use the same barycentric mapping).

Point location: dolfinx's bounding-box tree over the rank's *owned* cells proposes candidates,
the affine barycentric coordinates keep the cells that contain the point (smallest
coordinate >= -facet_tolerance, so points on facets are found; distance 0). A point found in
no cell of any rank (Loop subdivision moves vertices slightly off the coarse surface) gets as
candidates the closest owned cell (``compute_closest_entity``) and that cell's vertex
neighbours, with their distances, and uses *extrapolated* weights (the same formula, some
barycentric coordinates negative: still exact for linear fields) when the distance is at most
the tolerance of ``EmbeddingOptions``; otherwise ``InputError`` names the point and its
distance.

Parallel layout (deterministic, rank-count independent): every rank holds all shell points.
Among the candidates of all ranks a point takes the cell with the smallest distance, ties
broken by the cell's sorted input node indices (``geometry.input_global_indices``), so 1 and
N ranks pick the same cell. The rank owning that cell alone writes the row, with *local*
(owned + ghost) block columns, in ``Embedding.local``, so
``y = allreduce_sum(local @ U_local)`` is the full ``B U`` on every rank (each row lives on
exactly one rank: the sum adds zeros). ``Embedding.global_matrix`` gathers the rows with global
block columns (``index_map.local_to_global``) for inspection and serial use.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import MPI, dolfinx
from models.embedding.surface import Surface, boundary_surface

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_CHUNK = 100_000  # points per bounding-box query (bounds the candidate-pair arrays)


@dataclass(frozen=True)
class EmbeddingOptions:
    """Tolerances of the point location.

    Attributes:
        max_distance: absolute distance (mesh length unit) a point may lie outside the coarse
            mesh and still get extrapolated weights from the closest cell; ``None`` to use
            ``max_distance_rel`` instead.
        max_distance_rel: when ``max_distance`` is None, the allowed distance as a fraction of
            the longest edge of the closest cell (dimensionless).
        padding: padding of the bounding boxes (mesh length unit), so points on a facet
            (computed with round-off) still collide with their cells.
        tie_distance: distances to two cells closer than this (mesh length unit) count as
            equal; the cell is then chosen by its input node indices, independent of ranks.
        facet_tolerance: a point is inside a cell when its smallest barycentric coordinate
            is >= -facet_tolerance (dimensionless), so points on facets are found.

    """

    max_distance: float | None = None
    max_distance_rel: float = 0.25
    padding: float = 1e-10
    tie_distance: float = 1e-12
    facet_tolerance: float = 1e-12

    def __post_init__(self) -> None:
        if self.max_distance is not None and not self.max_distance >= 0.0:
            raise InputError(f"EmbeddingOptions.max_distance: expected >= 0, "
                             f"got {self.max_distance!r}")
        if not self.max_distance_rel >= 0.0:
            raise InputError(f"EmbeddingOptions.max_distance_rel: expected >= 0, "
                             f"got {self.max_distance_rel!r}")
        if not self.padding >= 0.0:
            raise InputError(f"EmbeddingOptions.padding: expected >= 0, got {self.padding!r}")
        if not self.facet_tolerance >= 0.0:
            raise InputError(f"EmbeddingOptions.facet_tolerance: expected >= 0, "
                             f"got {self.facet_tolerance!r}")
        if not self.tie_distance >= 0.0:
            raise InputError(f"EmbeddingOptions.tie_distance: expected >= 0, "
                             f"got {self.tie_distance!r}")


@dataclass(frozen=True)
class EmbeddingReport:
    """What the point location found (identical on every rank).

    Attributes:
        n_points: number of shell points.
        n_inside: points inside a coarse cell (up to the facet tolerance).
        n_extrapolated: points outside the mesh that use the closest cell's extrapolated
            weights.
        max_distance: largest distance of an extrapolated point to its cell (0 if none).

    """

    n_points: int
    n_inside: int
    n_extrapolated: int
    max_distance: float


@dataclass(frozen=True)
class Embedding:
    """B for one function space and one set of shell points.

    Attributes:
        local: ``(n_points, n_local_blocks)`` CSR with the rows owned by this rank, columns the
            rank's owned + ghost dof blocks of ``V``; zero rows for points owned elsewhere.
        owner: ``(n_points,)`` rank owning each point's row.
        cells: ``(n_points,)`` local cell index of each owned point's cell (-1 elsewhere).
        global_cols: ``(n_local_blocks,)`` global block index of each local column.
        n_global_blocks: number of dof blocks of ``V`` over all ranks.
        block_size: components per block (3 for a vector space).
        report: the point location statistics.
        comm: the mesh communicator.

    """

    local: sp.csr_matrix
    owner: IntArray
    cells: IntArray
    global_cols: IntArray
    n_global_blocks: int
    block_size: int
    report: EmbeddingReport
    comm: Any

    def apply(self, values: FloatArray) -> FloatArray:
        """``B @ U`` for local block values ``U`` (owned + ghost rows), summed over ranks.

        Args:
            values: ``(n_local_blocks,)`` or ``(n_local_blocks, k)`` array with ghosts up to
                date.

        Returns:
            The full ``(n_points,)`` / ``(n_points, k)`` result on every rank.

        """
        y = np.ascontiguousarray(self.local @ values)
        out = np.empty_like(y)
        self.comm.Allreduce(y, out, op=MPI.SUM)
        return out

    def global_matrix(self) -> sp.csr_matrix:
        """Gather B with global block columns onto every rank (``n_points x n_global_blocks``).

        Returns:
            The CSR matrix.

        """
        coo = self.local.tocoo()
        parts = self.comm.allgather((coo.row, self.global_cols[coo.col], coo.data))
        rows, cols, vals = (np.concatenate([p[i] for p in parts]) for i in range(3))
        return sp.csr_matrix((vals, (rows, cols)), shape=(self.local.shape[0],
                                                           self.n_global_blocks))


def _check_space(V: Any) -> None:
    """Raise InputError unless V is Lagrange on an affine (P1 geometry) tetrahedral mesh."""
    mesh = V.mesh
    if mesh.topology.cell_type != dolfinx.mesh.CellType.tetrahedron:
        raise InputError(f"V: expected a tetrahedral mesh, got {mesh.topology.cell_type}")
    if mesh.geometry.cmaps[0].degree != 1:
        raise InputError("V: mesh geometry must be affine (P1); curved cells are not supported")
    if V.element.needs_dof_transformations:
        raise InputError("V: element needs dof transformations (not Lagrange)")


def cell_vertices(mesh: Any, cells: npt.NDArray[np.int32]) -> FloatArray:
    """Coordinates ``(k, 4, 3)`` of the geometry nodes of ``cells`` (reference order)."""
    return mesh.geometry.x[mesh.geometry.dofmaps[0][cells]]


@dataclass(frozen=True)
class AffineMaps:
    """The affine maps ``x = x_0 + J X`` of all local (owned and ghost) cells.

    Attributes:
        origin: ``(n_cells, 3)`` first geometry node ``x_0`` of every cell.
        inverse: ``(n_cells, 3, 3)`` ``J^{-1}`` with ``J = [x_1 - x_0, x_2 - x_0, x_3 - x_0]``.

    """

    origin: FloatArray
    inverse: FloatArray

    def pull_back(self, cells: IntArray, points: FloatArray) -> FloatArray:
        """Map ``points[k]`` to reference coordinates ``X = J^{-1} (p - x_0)`` of ``cells[k]``.

        Outside the unit tetrahedron (some barycentric coordinate < 0) when extrapolating.
        """
        return np.einsum("kij,kj->ki", self.inverse[cells], points - self.origin[cells])


def affine_maps(mesh: Any) -> AffineMaps:
    """Pre-compute origin and inverse Jacobian of every local cell (P1 geometry)."""
    return affine_maps_of(mesh.geometry.x[mesh.geometry.dofmaps[0]])


def affine_maps_of(corners: FloatArray) -> AffineMaps:
    """Return the affine maps of tetrahedra given by their ``(n_cells, 4, 3)`` corners."""
    jac = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))
    return AffineMaps(origin=np.ascontiguousarray(corners[:, 0]), inverse=np.linalg.inv(jac))


def min_barycentric(ref: FloatArray) -> FloatArray:
    """Smallest barycentric coordinate ``min(1 - X - Y - Z, X, Y, Z)`` (< 0 outside)."""
    return np.minimum(1.0 - ref.sum(axis=1), ref.min(axis=1))


def _colliding_pairs(maps: AffineMaps, tree: Any, points: FloatArray, tol: float
                     ) -> tuple[IntArray, IntArray]:
    """``(point, cell)`` pairs of the owned cells containing each point (facets included).

    Bounding-box candidates are tested with the barycentric coordinates of the affine map
    (``min >= -tol``), in chunks to bound memory: much cheaper than
    ``dolfinx.geometry.compute_colliding_cells`` (a GJK distance per candidate).
    """
    pts_out, cells_out = [], []
    for start in range(0, points.shape[0], _CHUNK):
        chunk = points[start:start + _CHUNK]
        cand = dolfinx.geometry.compute_collisions_points(tree, chunk)
        cells = np.asarray(cand.array, dtype=np.int64)
        pts = np.repeat(np.arange(chunk.shape[0]), np.diff(cand.offsets))
        inside = min_barycentric(maps.pull_back(cells, chunk[pts])) >= -tol
        pts_out.append(pts[inside] + start)
        cells_out.append(cells[inside])
    return np.concatenate(pts_out).astype(np.int64), np.concatenate(cells_out)


def _vertex_neighbours(mesh: Any, cells: IntArray) -> tuple[IntArray, IntArray]:
    """``(i, cell)`` pairs: every owned cell sharing a vertex with ``cells[i]`` (itself too)."""
    top = mesh.topology
    top.create_connectivity(0, 3)
    c2v, v2c = top.connectivity(3, 0), top.connectivity(0, 3)
    verts = c2v.array.reshape(-1, 4)[cells].reshape(-1)
    start, count = v2c.offsets[verts], np.diff(v2c.offsets)[verts]
    first = np.repeat(np.cumsum(count) - count, count)
    nbr = v2c.array[np.repeat(start, count) + np.arange(first.size) - first]
    idx = np.repeat(np.repeat(np.arange(cells.size), 4), count)
    keep = nbr < top.index_map(3).size_local
    pairs = np.unique(np.stack([idx[keep], nbr[keep]], axis=1), axis=0)
    return pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)


def _closest_pairs(mesh: Any, tree: Any, owned: npt.NDArray[np.int32], points: FloatArray,
                   miss: IntArray) -> tuple[IntArray, IntArray, FloatArray]:
    """Closest owned cell of each missed point and its vertex neighbours, with distances.

    The neighbours are the cells that may be equally close (closest point on a shared facet,
    edge or vertex).
    """
    geom = dolfinx.geometry
    if owned.size == 0 or miss.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    mid = geom.create_midpoint_tree(mesh, 3, owned)
    closest = np.asarray(geom.compute_closest_entity(tree, mid, mesh, points[miss]), np.int64)
    i, cells = _vertex_neighbours(mesh, closest)
    d2 = geom.squared_distance(mesh, 3, cells.astype(np.int32), points[miss[i]])
    return miss[i], cells, np.sqrt(np.maximum(d2, 0.0))


def candidate_cells(mesh: Any, maps: AffineMaps, points: FloatArray, options: EmbeddingOptions
                    ) -> tuple[IntArray, IntArray, FloatArray]:
    """Candidate owned cells of every point and their distances (0 inside) (collective).

    Args:
        mesh: the dolfinx mesh.
        maps: its affine cell maps.
        points: ``(n, 3)`` points (the same on every rank).
        options: tolerances.

    Returns:
        ``(point, cell, distance)`` arrays: the cells containing a point, or, for a point in
        no cell of any rank, the closest owned cell and its vertex neighbours. A point inside
        another rank's cell gets no candidate here, as a point found inside a cell gets no
        closest cell on one rank: every partition has the candidates of the serial run.

    """
    owned = np.arange(mesh.topology.index_map(3).size_local, dtype=np.int32)
    tree = dolfinx.geometry.bb_tree(mesh, 3, padding=options.padding, entities=owned)
    pt_in, cell_in = _colliding_pairs(maps, tree, points, options.facet_tolerance)
    inside = np.zeros(points.shape[0], dtype=np.int8)
    inside[pt_in] = 1
    miss = np.flatnonzero(_allreduce(mesh.comm, inside, MPI.MAX) == 0)
    exact_tree = dolfinx.geometry.bb_tree(mesh, 3, entities=owned)
    pt_out, cell_out, d_out = _closest_pairs(mesh, exact_tree, owned, points, miss)
    return (np.concatenate([pt_in, pt_out]), np.concatenate([cell_in, cell_out]),
            np.concatenate([np.zeros(pt_in.size), d_out]))


def cell_keys(mesh: Any, cells: IntArray) -> IntArray:
    """Rank-independent ``(k, 4)`` key of each cell: its sorted input node indices."""
    igi = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)
    return np.sort(igi[mesh.geometry.dofmaps[0][cells]], axis=1)


def _allreduce(comm: Any, values: npt.NDArray[Any], op: Any) -> npt.NDArray[Any]:
    """Element-wise Allreduce of a numpy array."""
    out = np.empty_like(values)
    comm.Allreduce(np.ascontiguousarray(values), out, op=op)
    return out


def choose_cells(comm: Any, n_points: int, pt: IntArray, dist: FloatArray, keys: IntArray,
                 tie: float) -> tuple[npt.NDArray[np.bool_], FloatArray]:
    """Select one candidate per point over all ranks, independent of the partition.

    The chosen cell has the smallest distance (ties within ``tie``), then the
    lexicographically smallest key (sorted input node indices), so 1 and N ranks choose the
    same cell, which matters for extrapolated points (different cells extrapolate differently).

    Args:
        comm: communicator.
        n_points: number of points.
        pt: candidate's point.
        dist: candidate's distance.
        keys: candidate's ``(k, 4)`` cell key.
        tie: distances within ``tie`` of the smallest count as equal.

    Returns:
        ``(keep, dmin)``: mask of the chosen candidates on this rank (at most one per point
        over all ranks) and the smallest distance of every point.

    """
    dloc = np.full(n_points, np.inf)
    np.minimum.at(dloc, pt, dist)
    dmin = _allreduce(comm, dloc, MPI.MIN)
    keep = dist <= dmin[pt] + tie
    big = np.iinfo(np.int64).max
    for k in range(keys.shape[1]):
        kmin = np.full(n_points, big, dtype=np.int64)
        np.minimum.at(kmin, pt[keep], keys[keep, k])
        keep &= keys[:, k] == _allreduce(comm, kmin, MPI.MIN)[pt]
    return keep, dmin


def _longest_edge(verts: FloatArray) -> FloatArray:
    """Longest edge length of each ``(4, 3)`` cell."""
    i, j = np.triu_indices(4, 1)
    return np.linalg.norm(verts[:, i] - verts[:, j], axis=2).max(axis=1)


def locate(mesh: Any, maps: AffineMaps, points: FloatArray, options: EmbeddingOptions
           ) -> tuple[IntArray, FloatArray]:
    """Choose the cell of every point (collective).

    Args:
        mesh: the dolfinx mesh.
        maps: its affine cell maps.
        points: ``(n, 3)`` points (the same on every rank).
        options: tolerances.

    Returns:
        ``(cells, dist)``: the local cell per point on the rank that owns it (-1 elsewhere)
        and the distance of every point to its chosen cell (0 inside, inf if no cell).

    Raises:
        InputError: for a point outside the tolerance (the first one is named).

    """
    pt, cell, dist = candidate_cells(mesh, maps, points, options)
    keep, dmin = choose_cells(mesh.comm, points.shape[0], pt, dist, cell_keys(mesh, cell),
                              options.tie_distance)
    cells = np.full(points.shape[0], -1, dtype=np.int64)
    cells[pt[keep]] = cell[keep]
    allowed = np.full(points.shape[0], -np.inf)
    mine = np.flatnonzero(cells >= 0)
    allowed[mine] = (options.max_distance if options.max_distance is not None else
                     options.max_distance_rel * _longest_edge(
                         cell_vertices(mesh, cells[mine].astype(np.int32))))
    _check_distances(mesh.comm, points, dmin, _allreduce(mesh.comm, allowed, MPI.MAX))
    return cells, dmin


def _check_distances(comm: Any, points: FloatArray, dist: FloatArray, allowed: FloatArray
                     ) -> None:
    """Raise InputError (on every rank) naming the first point farther than allowed."""
    bad = np.flatnonzero(~(dist <= allowed))
    if bad.size:
        i = int(bad[0])
        raise InputError(f"shell point {i} at {points[i].tolist()} is outside the coarse mesh "
                         f"by {dist[i]:.6g} (> allowed {allowed[i]:.6g}); "
                         f"{bad.size} point(s) outside the tolerance")


def basis_weights(V: Any, maps: AffineMaps, cells: IntArray, points: FloatArray
                  ) -> FloatArray:
    """Values ``phi_j(X)`` of the element basis at the points' reference coordinates.

    Args:
        V: the function space (its scalar basix element is tabulated).
        maps: the affine cell maps of ``V.mesh``.
        cells: ``(k,)`` local cells.
        points: ``(k, 3)`` points.

    Returns:
        ``(k, n_cell_dofs)`` weights in the element's local dof order.

    """
    ref = maps.pull_back(cells, points)
    return V.element.basix_element.tabulate(0, ref)[0, :, :, 0]


def _local_matrix(V: Any, maps: AffineMaps, cells: IntArray, points: FloatArray,
                  rows: IntArray, n_points: int) -> sp.csr_matrix:
    """CSR with the rows ``rows`` (cells ``cells``) in local block columns of V."""
    imap = V.dofmap.index_map
    n_cols = imap.size_local + imap.num_ghosts
    w = basis_weights(V, maps, cells, points) if rows.size else np.zeros((0, 0))
    cols = V.dofmap.list[cells] if rows.size else np.zeros((0, 0), dtype=np.int32)
    r = np.repeat(rows, w.shape[1] if rows.size else 0)
    return sp.csr_matrix((w.reshape(-1), (r, cols.reshape(-1))), shape=(n_points, n_cols))


def build_embedding(V: Any, points: FloatArray, options: EmbeddingOptions | None = None
                    ) -> Embedding:
    """Build B for the function space ``V`` (scalar or vector Lagrange P1/P2) at ``points``.

    Args:
        V: a dolfinx Lagrange FunctionSpace on an affine tetrahedral mesh.
        points: ``(n, 3)`` shell points, identical on every rank (collective call).
        options: point location tolerances.

    Returns:
        The ``Embedding`` (collective; every rank gets the same owner and report).

    Raises:
        InputError: wrong space, or a point outside the mesh by more than the tolerance
            (the message names the point index and its distance).

    """
    opts = options or EmbeddingOptions()
    _check_space(V)
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points: expected shape (n, 3), got {points.shape}")
    comm = V.mesh.comm
    maps = affine_maps(V.mesh)
    cells, dist = locate(V.mesh, maps, points, opts)
    owner = _allreduce(comm, np.where(cells >= 0, comm.rank, comm.size), MPI.MIN)
    rows = np.flatnonzero(cells >= 0)
    local = _local_matrix(V, maps, cells[rows], points[rows], rows, points.shape[0])
    imap = V.dofmap.index_map
    gcols = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))
    return Embedding(local=local, owner=owner.astype(np.int64), cells=cells,
                     global_cols=np.asarray(gcols, dtype=np.int64),
                     n_global_blocks=int(imap.size_global), block_size=int(V.dofmap.index_map_bs),
                     report=_report(dist), comm=comm)


def _report(dist: FloatArray) -> EmbeddingReport:
    """Point location statistics from the chosen distances."""
    n_out = int(np.count_nonzero(dist > 0.0))
    return EmbeddingReport(n_points=int(dist.size), n_inside=int(dist.size) - n_out,
                           n_extrapolated=n_out, max_distance=float(dist.max(initial=0.0)))


def apply_to_function(emb: Embedding, u: Any) -> FloatArray:
    """Shell values ``B u`` of a dolfinx Function on ``V`` (ghosts updated first).

    Args:
        emb: the embedding built for ``u``'s function space.
        u: a dolfinx Function.

    Returns:
        ``(n_points, bs)`` values on every rank (collective).

    """
    u.x.scatter_forward()
    return emb.apply(u.x.array.reshape(-1, emb.block_size))


def add_transpose_to_function(emb: Embedding, forces: FloatArray, f: Any) -> None:
    """Accumulate ``B^T forces`` into the Function ``f`` (two-way coupling, Remillard & Kry).

    Each point's force enters once (on its owner rank, possibly into a ghost block), then the
    ghost contributions are summed into their owners and ghosts refreshed.

    Args:
        emb: the embedding built for ``f``'s function space.
        forces: ``(n_points, bs)`` shell forces, identical on every rank.
        f: a dolfinx Function; its values are incremented (collective).

    """
    arr = f.x.array.reshape(-1, emb.block_size)
    owned = f.function_space.dofmap.index_map.size_local
    arr[owned:] = 0.0
    arr += emb.local.T @ np.asarray(forces, dtype=np.float64).reshape(-1, emb.block_size)
    f.x.scatter_reverse(dolfinx.la.InsertMode.add)
    f.x.scatter_forward()


def mesh_surface(mesh: Any) -> Surface:
    """Outward boundary surface of a distributed dolfinx tet mesh, identical on every rank.

    Every rank sends the input (global) node indices of its owned cells and the coordinates
    of its nodes; the gathered ``(points, tets)`` use the input node numbering
    (``mesh.geometry.input_global_indices``), compacted to the nodes cells use, so the
    surface is independent of the number of ranks and of dolfinx's reordering.

    Args:
        mesh: a dolfinx tetrahedral mesh with affine (P1) geometry.

    Returns:
        The ``Surface``; ``node_map`` holds the input node indices.

    """
    geo = mesh.geometry
    if geo.cmaps[0].degree != 1:
        raise InputError("mesh: geometry must be affine (P1) to extract the boundary surface")
    n_owned = mesh.topology.index_map(3).size_local
    igi = np.asarray(geo.input_global_indices, dtype=np.int64)
    parts = mesh.comm.allgather((igi[geo.dofmaps[0][:n_owned]], igi, geo.x[:, :3].copy()))
    tets = np.concatenate([p[0] for p in parts])
    nodes, inverse = np.unique(np.concatenate([p[1] for p in parts]), return_index=True)
    xs = np.concatenate([p[2] for p in parts])[inverse]
    surf = boundary_surface(xs, np.searchsorted(nodes, tets))
    return Surface(vertices=surf.vertices, faces=surf.faces, node_map=nodes[surf.node_map])


__all__ = ["Embedding", "EmbeddingOptions", "EmbeddingReport", "add_transpose_to_function",
           "apply_to_function", "build_embedding", "mesh_surface"]
