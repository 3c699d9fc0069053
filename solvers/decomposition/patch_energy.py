"""The global shell energy restricted to one patch's owned vertices (a block of W).

For the owned set ``I`` of a patch the block problem is ``min_{x_I} W(x_I, x_rest)`` with every
other vertex held at its current value. Only stencils touching ``I`` depend on ``x_I``:

* edges and faces of the one-ring of ``I`` (the draft's patch),
* hinges with *any* of their four vertices in ``I``: a hinge ``[i, j, k, l]`` whose opposite
  vertex ``k`` is owned but whose edge ``(i, j)`` is not reaches the far vertex ``l`` outside
  the one-ring, so both its faces are added (the draft's one-ring patch alone would drop it),
* penalty rows (clusters) whose support meets ``I``: ``W_P`` couples the whole support, so
  those rows are kept with all their columns (the non-owned ones fixed).

These stencils are gathered into a local :class:`ShellEnergy` on a local numbering (owned
vertices first) whose rest data is *sliced* from the global rest state (never recomputed), so
``grad_I W_local = grad_I W`` and ``hess_II W_local = hess_II W`` exactly: the union of patch
problems is a block (Jacobi / Gauss-Seidel) method for the same global W. Stencils of the
local energy that do not touch ``I`` only add a constant.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.shell.dofs import check_positions
from models.shell.energy import ShellEnergy, ShellEval, ShellParams
from models.shell.rest import RestState
from models.shell.topology import ShellTopology


@dataclass(frozen=True, eq=False)
class ShellProblem:
    """A global shell problem: what every rank needs to build its patch energies.

    Attributes:
        topology: Global connectivity.
        rest: Global rest state.
        params: Stiffnesses and Hessian options.
        H: (c, n) cluster matrix (None when ``params.k_P == 0``).
        target: (n, 3) penalty target y.

    """

    topology: ShellTopology
    rest: RestState
    params: ShellParams
    H: sp.csr_matrix | None
    target: np.ndarray

    def energy(self) -> ShellEnergy:
        """Build the global (monolithic) energy with the target set."""
        energy = ShellEnergy(self.topology, self.rest, self.params, H=self.H)
        energy.set_target(self.target)
        return energy


def _stencil_faces(topology: ShellTopology, owned: np.ndarray) -> np.ndarray:
    """Sorted global faces of every edge / face / hinge stencil touching ``owned``."""
    one_ring = owned[topology.faces].any(axis=1)
    hinges = owned[topology.hinges].any(axis=1)
    wing = topology.edge_faces[topology.hinge_edge[hinges]].reshape(-1)
    faces = np.flatnonzero(one_ring)
    return np.union1d(faces, wing[wing >= 0])


def _penalty_rows(H: sp.csr_matrix | None, interior: np.ndarray) -> np.ndarray:
    """Cluster rows whose support meets ``interior``."""
    if H is None:
        return np.zeros(0, dtype=np.int64)
    return np.unique(sp.csc_matrix(H)[:, interior].tocoo().row).astype(np.int64)


def _local_vertices(interior: np.ndarray, faces: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Global ids of the local numbering: owned vertices first, then the fixed halo."""
    halo = np.setdiff1d(np.union1d(np.unique(faces), support), interior)
    return np.concatenate([interior, halo]).astype(np.int64)


def _edge_index(edges: np.ndarray, n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Global edge index of vertex pairs (a, b) (edges are sorted lexicographically)."""
    keys = edges[:, 0] * n + edges[:, 1]
    return np.searchsorted(keys, np.minimum(a, b) * n + np.maximum(a, b))


def slice_rest(problem: ShellProblem, local: np.ndarray, faces: np.ndarray,
               ids: tuple[np.ndarray, np.ndarray]) -> RestState:
    """Rest state of a local topology sliced from the global rest state.

    Args:
        problem: The global problem.
        local: Global id of each local vertex.
        faces: Global index of each local face (same order as the local topology's faces).
        ids: Global index of each local edge and of each local hinge (:func:`global_ids`).

    Hinge angles need no sign fix: a local hinge ``[j, i, l, k]`` (renumbering swapped the
    edge's vertex order) has the same signed angle as ``[i, j, k, l]``, since the two face
    normals and the edge direction all swap together.

    """
    r, (ge, gh) = problem.rest, ids
    return RestState(positions=r.positions[local], rest_lengths=r.rest_lengths[ge],
                     rest_areas=r.rest_areas[faces], rest_angles=r.rest_angles[gh],
                     hinge_weights=r.hinge_weights[gh], vertex_areas=r.vertex_areas[local])


def global_ids(topology: ShellTopology, local: np.ndarray, topo: ShellTopology
               ) -> tuple[np.ndarray, np.ndarray]:
    """Global index of each edge and of each hinge (by its interior edge) of ``topo``.

    ``topo``: a local topology on the global vertices ``local``.
    """
    edges = _edge_index(topology.edges, topology.n_vertices, local[topo.edges[:, 0]],
                        local[topo.edges[:, 1]])
    edge_to_hinge = np.full(topology.n_edges, -1, dtype=np.int64)
    edge_to_hinge[topology.hinge_edge] = np.arange(topology.hinge_edge.size)
    return edges, edge_to_hinge[edges[topo.hinge_edge]]


def leading_rows(matrix: sp.csr_matrix, m: int) -> sp.csr_matrix:
    """Return the first ``m`` rows of a CSR matrix, sharing its arrays.

    A patch numbers its owned vertices first, so its rows of the Hessian are the leading
    ``3 |I|`` rows of the local one; scipy's row slicing would copy them at every evaluation
    (scipy still copies when the rows hold less than half of the entries).
    """
    end = int(matrix.indptr[m])
    return sp.csr_matrix((matrix.data[:end], matrix.indices[:end], matrix.indptr[: m + 1]),
                         shape=(m, matrix.shape[1]), copy=False)


_OWNED_KIND = {"membrane_edge": "edges", "membrane_area": "faces", "bending": "hinges",
               "penalty": "rows", "flip_barrier": "flip_faces"}
"""Stencil kind of each term counted in the owned energy."""


class PatchEnergy:
    """``x_I -> W(x_I, x_fixed)`` for one owned set I (the ShellEnergy interface, n = |I|).

    Args:
        problem: The global problem.
        interior: Sorted global ids of the owned vertices I.

    Attributes:
        interior: Global ids of the owned vertices (local 0..|I|-1).
        local: Global ids of all local vertices (owned first, then the fixed halo).
        halo: Global ids of the fixed vertices the block depends on.
        hinge_ids: Global index of each hinge of the local energy.

    """

    def __init__(self, problem: ShellProblem, interior: np.ndarray) -> None:
        n = problem.topology.n_vertices
        self.interior = np.asarray(interior, dtype=np.int64)
        if self.interior.size == 0:
            raise InputError("interior: a patch needs at least one owned vertex")
        owned = np.zeros(n, dtype=bool)
        owned[self.interior] = True
        faces = _stencil_faces(problem.topology, owned)
        rows = _penalty_rows(problem.H, self.interior)
        h_rows = problem.H[rows] if problem.H is not None and rows.size else None
        support = np.unique(h_rows.indices) if h_rows is not None else np.zeros(0, np.int64)
        self.local = _local_vertices(self.interior, problem.topology.faces[faces], support)
        self.halo = self.local[self.interior.size:]
        self.energy = self._local_energy(problem, faces, h_rows)
        self._x = problem.rest.positions[self.local].copy()
        self._hess_map: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._owned_terms = self._owned_stencils(h_rows)

    def _local_energy(self, problem: ShellProblem, faces: np.ndarray,
                      h_rows: sp.csr_matrix | None) -> ShellEnergy:
        """ShellEnergy on the local numbering with sliced rest data, H rows and target."""
        g2l = np.full(problem.topology.n_vertices, -1, dtype=np.int64)
        g2l[self.local] = np.arange(self.local.size)
        topo = ShellTopology.from_faces(g2l[problem.topology.faces[faces]], self.local.size)
        ids = global_ids(problem.topology, self.local, topo)
        self.hinge_ids = ids[1]
        rest = slice_rest(problem, self.local, faces, ids)
        params = problem.params if h_rows is not None else replace(problem.params, k_P=0.0)
        h_local = sp.csr_matrix(h_rows[:, self.local]) if h_rows is not None else None
        self._h_local = h_local
        energy = ShellEnergy(topo, rest, params, H=h_local)
        energy.set_target(problem.target[self.local])
        return energy

    def set_hinge_branch(self, branch: np.ndarray | None) -> None:
        """Give the local hinges their entries of the global reference angles (Hn,) or None.

        :meth:`models.shell.energy.ShellEnergy.set_hinge_branch`; a local hinge has the same
        signed angle as its global one (see :func:`slice_rest`).
        """
        self.energy.set_hinge_branch(None if branch is None else branch[self.hinge_ids])

    def _is_owned(self, stencils: np.ndarray) -> np.ndarray:
        """Stencils (local ids) whose smallest global vertex is owned by this patch."""
        if stencils.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        return np.isin(self.local[stencils].min(axis=1), self.interior)

    def _owned_stencils(self, h_rows: sp.csr_matrix | None) -> dict[str, np.ndarray]:
        """Mask the stencils assigned to this patch.

        Each global stencil goes to exactly one patch: the owner of its smallest global
        vertex (a penalty row: of its smallest support vertex).
        """
        topo = self.energy.topology
        out = {"edges": self._is_owned(topo.edges), "faces": self._is_owned(topo.faces),
               "hinges": self._is_owned(topo.hinges)}
        out["flip_faces"] = out["faces"][self.energy.flip_faces]
        if h_rows is not None:
            first = np.minimum.reduceat(h_rows.indices, h_rows.indptr[:-1])
            out["rows"] = np.isin(first, self.interior)
        return out

    def owned_energy(self, elements: dict[str, np.ndarray] | None = None) -> float:
        """Energy of the stencils assigned to this patch at the current state.

        Summed over all patches this is exactly W(x) (every stencil counted once), which
        makes global energy comparisons (line search, safeguards) a scalar reduction.
        ``elements``: the per-stencil energies (:attr:`ShellEval.elements`) of an evaluation
        of :attr:`energy` at the current state; their owned entries are summed (no second
        pass over the stencils). Without it the local energy is evaluated (order 0).
        """
        if elements is None:
            elements = self.energy.evaluate(self._x, order=0).elements
        return self._owned_sum(elements)

    def _owned_sum(self, elements: dict[str, np.ndarray]) -> float:
        """Sum of the owned entries of the per-stencil energies (+inf if not finite)."""
        total = sum(float(elements[term][self._owned_terms[kind]].sum())
                    for term, kind in _OWNED_KIND.items() if term in elements)
        return float(total) if np.isfinite(total) else np.inf

    @property
    def n_vertices(self) -> int:
        """Number of unknown (owned) vertices |I|."""
        return int(self.interior.size)

    @property
    def n_free_dofs(self) -> int:
        """3 |I|."""
        return 3 * self.n_vertices

    def set_state(self, x: np.ndarray) -> None:
        """Take owned and halo values from the global positions x (n, 3)."""
        self._x[:] = x[self.local]

    def owned_values(self) -> np.ndarray:
        """Return the current owned positions (|I|, 3) (a copy)."""
        return self._x[: self.n_vertices].copy()

    def _full(self, x_free: np.ndarray) -> np.ndarray:
        """Local positions with the owned rows replaced by ``x_free``."""
        xf = check_positions(np.asarray(x_free).reshape(-1, 3), self.n_vertices, "x")
        full = self._x.copy()
        full[: self.n_vertices] = xf
        return full

    def _free_block(self, hess: sp.csr_matrix) -> sp.csr_matrix:
        """Owned-owned block of the local Hessian on a fixed pattern (map built once)."""
        m = self.n_free_dofs
        if self._hess_map is None:
            marks = sp.csr_matrix((np.arange(1.0, hess.nnz + 1), hess.indices, hess.indptr),
                                  shape=hess.shape)[:m, :m].tocsr()
            marks.sort_indices()
            self._hess_map = (marks.indptr.copy(), marks.indices.copy(),
                              marks.data.astype(np.int64) - 1)
        indptr, indices, source = self._hess_map
        return sp.csr_matrix((hess.data[source], indices, indptr), shape=(m, m))

    def evaluate(self, x: np.ndarray, order: int = 2, hessian: str | None = None) -> ShellEval:
        """Value (local stencils), owned gradient (3|I|,) and owned Hessian block."""
        ev = self.energy.evaluate(self._full(x), order, hessian)  # type: ignore[arg-type]
        m = self.n_free_dofs
        grad = ev.grad[:m].copy() if ev.grad is not None else None
        hess = self._free_block(ev.hess) if ev.hess is not None else None
        g = sp.csr_matrix(ev.penalty_factor[:, :m]) if ev.penalty_factor is not None else None
        return ShellEval(value=ev.value, grad=grad, hess=hess, penalty_factor=g, terms=ev.terms)

    def value(self, x: np.ndarray) -> float:
        """Energy of the local stencils with the owned rows set to ``x``."""
        return self.energy.value(self._full(x))

    def gradient_at_state(self) -> np.ndarray:
        """Owned gradient (3|I|,) at the current state (= the global gradient's owned rows)."""
        return self.evaluate(self._x[: self.n_vertices], order=1).grad  # type: ignore[return-value]
