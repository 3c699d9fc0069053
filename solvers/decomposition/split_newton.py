r"""The whole problem distributed by stencils: monolithic Newton with the low-rank penalty.

The reference parallel method at scale (MISSION.md section 7). Every rank ``r`` owns a vertex
set ``I_r`` (the cluster partition merged to the number of ranks, :mod:`.patches`) and

* evaluates only the stencils touching ``I_r`` (a :class:`~.patch_energy.PatchEnergy`: edges,
  faces, hinges with a vertex in ``I_r``), so its local gradient rows ``I_r`` and Hessian rows
  ``I_r`` (all columns) are exactly the global ones; the energy is the sum over ranks of each
  rank's *owned* stencils (every stencil counted once), an ``Allreduce``; the gradient's owned
  rows are allgathered (3n numbers) so every rank runs the same Newton decisions;
* holds only its rows of the Newton matrix. The penalty ``W_P = k_P ||H (x - y)||^2`` has the
  Hessian ``G^T G`` with ``G = sqrt(2 k_P) (H kron I_3)`` (3c x 3n), which is dense over each
  cluster support: assembled it fills in. As in :class:`solvers.linear.AugmentedPenaltySolver`
  the step solves the quasi-definite augmented system

  .. math::  \begin{bmatrix} A + \tau I & G^T \\ G & -I \end{bmatrix}
             \begin{bmatrix} dx \\ \mu \end{bmatrix} = \begin{bmatrix} -g \\ 0 \end{bmatrix},

  eliminating ``mu = G dx`` gives ``(A + tau I + G^T G) dx = -g``. Its inertia is
  ``In(-I) + In(A + tau I + G^T G)`` (Haynsworth), so more than ``3c`` negative pivots
  (MUMPS ``INFOG(12)``) mean the reduced Hessian is indefinite and the Newton solver shifts;
* the augmented matrix is a ``MATMPIAIJ`` whose rows are split by rank (rank r: the dofs of
  ``I_r``, then the multipliers of the clusters whose smallest support vertex is in ``I_r``);
  its pattern is set once (``MatSetPreallocationCOO``), values by ``MatSetValuesCOO`` (same
  nonzero state: MUMPS' analysis runs once), factorised by MUMPS LDL^T (``SYM = 2``) with the
  controls of :func:`solvers.linear.set_mumps_controls`.

The Newton iteration itself (line search, shifts, tolerances, stagnation stop) is
:class:`solvers.shell_newton.ShellNewtonSolver`, unchanged: this module gives it an energy
whose value / gradient are reduced over ranks and a linear system that is distributed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import MPI, PETSc, begin_petsc_log
from models.shell.dofs import stencil_dofs
from models.shell.energy import ShellEval
from models.shell.penalty import PenaltyOperator, penalty_factor
from solvers.decomposition.patch_energy import PatchEnergy, ShellProblem, leading_rows
from solvers.decomposition.patches import bisect_partition
from solvers.decomposition.split_multigrid import SplitMultigridSystem
from solvers.linear import (
    DiagonalScale,
    FactorReport,
    LinearSolverOptions,
    coo_aij,
    factor_event_totals,
    factor_ksp,
    factor_status,
    setup_pc,
)
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver, ShellSolveReport


def rank_of_vertices(problem: ShellProblem, partition: np.ndarray | None,
                     size: int) -> np.ndarray:
    """(n,) owning rank of each vertex.

    Whole sets of the cluster partition grouped into ``size`` parts of nearly equal vertex
    counts (:func:`.patches.bisect_partition`) when given, else contiguous index ranges.
    """
    n = problem.topology.n_vertices
    if partition is not None and size > 1:
        return bisect_partition(problem.rest.positions, partition, size)
    return np.minimum((np.arange(n) * size) // n, size - 1).astype(np.int64)


@dataclass(frozen=True, eq=False)
class SplitLayout:
    """Global PETSc numbering of the augmented unknowns ``[dx; mu]`` split by rank.

    Rank r owns the PETSc rows ``offsets[r] .. offsets[r + 1] - 1``: first the 3 dofs of each
    of its vertices (sorted), then the 3 multipliers of each of its clusters (sorted).

    Attributes:
        vertex_rank: (n,) rank owning each vertex.
        cluster_rank: (c,) rank owning each penalty row (owner of its smallest support vertex).
        vertex_index: (n,) PETSc index of dof ``3 v`` (dof ``3 v + k`` is this + k).
        cluster_index: (c,) PETSc index of multiplier ``3 c`` (+ k for coordinate k).
        offsets: (size + 1,) PETSc row ranges of the ranks.
        vertex_order: (n,) vertices ordered by rank then index (the allgather order).

    """

    vertex_rank: np.ndarray
    cluster_rank: np.ndarray
    vertex_index: np.ndarray
    cluster_index: np.ndarray
    offsets: np.ndarray
    vertex_order: np.ndarray

    @classmethod
    def build(cls, vertex_rank: np.ndarray, H: sp.csr_matrix | None,
              size: int) -> SplitLayout:
        """Build the numbering rank by rank (see the class docstring)."""
        c = 0 if H is None else H.shape[0]
        first = (np.minimum.reduceat(H.indices, H.indptr[:-1]) if H is not None and c
                 else np.zeros(0, np.int64))
        cluster_rank = vertex_rank[first].astype(np.int64)
        n_v = np.bincount(vertex_rank, minlength=size)
        n_c = np.bincount(cluster_rank, minlength=size)
        offsets = np.concatenate([[0], np.cumsum(3 * (n_v + n_c))]).astype(np.int64)
        order = np.argsort(vertex_rank, kind="stable")
        vertex_index = np.empty(vertex_rank.size, dtype=np.int64)
        local_v = np.arange(vertex_rank.size) - np.repeat(np.cumsum(n_v) - n_v, n_v)
        vertex_index[order] = offsets[vertex_rank[order]] + 3 * local_v
        c_order = np.argsort(cluster_rank, kind="stable")
        cluster_index = np.empty(c, dtype=np.int64)
        local_c = np.arange(c) - np.repeat(np.cumsum(n_c) - n_c, n_c)
        cluster_index[c_order] = (offsets[cluster_rank[c_order]] + 3 * n_v[cluster_rank[c_order]]
                                  + 3 * local_c)
        return cls(vertex_rank=vertex_rank.astype(np.int64), cluster_rank=cluster_rank,
                   vertex_index=vertex_index, cluster_index=cluster_index, offsets=offsets,
                   vertex_order=order.astype(np.int64))


class OwnedRows:
    """Rows of the Hessian held by one rank (owned vertex dofs x local columns).

    Stands in for the global Hessian in :class:`ShellNewtonSolver`, which only reads its
    diagonal (for the shift scale); the diagonal is allgathered, so every rank computes the
    same shift.

    Attributes:
        matrix: (3|I|, 3 n_local) CSR rows of the local Hessian (local column numbering).
        full_diagonal: (3n,) the global Hessian diagonal (identical on every rank).

    """

    def __init__(self, matrix: sp.csr_matrix, full_diagonal: np.ndarray) -> None:
        self.matrix, self.full_diagonal = matrix, full_diagonal

    def diagonal(self) -> np.ndarray:
        """Return the global diagonal (3n,)."""
        return self.full_diagonal


class SplitShellEnergy:
    """W(x) evaluated by stencils across ranks (the ShellEnergy interface on every rank).

    Args:
        problem: The global problem (its ``params.penalty_hessian`` is forced to "low_rank":
            the penalty Hessian is carried by G in the augmented system).
        layout: Ownership and numbering.
        comm: Communicator.

    Attributes:
        patch: This rank's stencils as a :class:`PatchEnergy` (owned vertices first).
        topology: Global topology (for diagnostics of the Newton solver).
        rest: Global rest state.

    """

    def __init__(self, problem: ShellProblem, layout: SplitLayout, comm: Any) -> None:
        low = replace(problem, params=replace(problem.params, penalty_hessian="low_rank"))
        self.comm, self.layout = comm, layout
        self.topology, self.rest = problem.topology, problem.rest
        self.target = np.array(problem.target, dtype=np.float64)
        """The global penalty target y (n, 3), the same on every rank."""
        owned = np.flatnonzero(layout.vertex_rank == comm.rank)
        self.patch = PatchEnergy(low, owned)
        counts = np.bincount(layout.vertex_rank, minlength=comm.size)
        self._counts3 = 3 * counts
        self._displs3 = np.concatenate([[0], np.cumsum(self._counts3)[:-1]])
        self._dof_order = stencil_dofs(layout.vertex_order[:, None]).reshape(-1)
        self.owned_dofs = stencil_dofs(self.patch.interior[:, None]).reshape(-1)
        """Global dofs of this rank's vertices, vertex-major (the order of its rows)."""
        self._diagonal = DiagonalScale()  # the own rows' diagonal, positions found once

    @property
    def n_vertices(self) -> int:
        """Global number of vertices n."""
        return self.topology.n_vertices

    def hessian_rows_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """``(indptr, indices)`` of this rank's Hessian rows (local columns), as evaluated."""
        pattern = self.patch.energy.pattern
        m = self.patch.n_free_dofs
        return pattern.indptr[: m + 1], pattern.indices[: int(pattern.indptr[m])]

    def allgather_owned(self, owned: np.ndarray) -> np.ndarray:
        """Full (3n,) vector from every rank's owned dof values (3|I_r|,), identical on all."""
        buf = np.empty(int(self._counts3.sum()))
        self.comm.Allgatherv([np.ascontiguousarray(owned, dtype=np.float64), MPI.DOUBLE],
                             [buf, self._counts3, self._displs3, MPI.DOUBLE])
        full = np.empty_like(buf)
        full[self._dof_order] = buf
        return full

    def set_target(self, y: np.ndarray, normals: bool = True) -> None:
        """Set the global penalty target y (n, 3) and this rank's local energy's share of it.

        ``normals``: as :meth:`models.shell.energy.ShellEnergy.set_target` (False keeps the
        flip barrier's reference normals, within a solve in which y moves).
        """
        self.target = np.array(y, dtype=np.float64)
        self.patch.energy.set_target(self.target[self.patch.local], normals=normals)

    def _local_x(self, x: np.ndarray) -> np.ndarray:
        """Local positions (owned, then halo) from the global x (n, 3)."""
        return np.asarray(x, dtype=np.float64).reshape(-1, 3)[self.patch.local]

    def value(self, x: np.ndarray, elements: dict[str, np.ndarray] | None = None) -> float:
        """``W(x) = sum_r`` (energy of rank r's owned stencils), reduced over ranks.

        ``elements``: per-stencil energies of the local energy at ``x`` when already
        evaluated (:meth:`PatchEnergy.owned_energy`).
        """
        self.patch.set_state(np.asarray(x, dtype=np.float64).reshape(-1, 3))
        return float(self.comm.allreduce(self.patch.owned_energy(elements), op=MPI.SUM))

    def evaluate(self, x: np.ndarray, order: int = 2, hessian: str | None = None) -> ShellEval:
        """Reduced value, full gradient (allgathered) and this rank's Hessian rows.

        The value is the owned share of the same local evaluation (one pass).
        """
        xl = self._local_x(x)
        ev = self.patch.energy.evaluate(xl, order, hessian)  # type: ignore[arg-type]
        m = self.patch.n_free_dofs
        value = self.value(x, ev.elements)
        grad = self.allgather_owned(ev.grad[:m]) if ev.grad is not None else None
        hess = None
        if ev.hess is not None:
            rows = leading_rows(ev.hess, m)
            hess = OwnedRows(rows, self.allgather_owned(self._diagonal.diagonal(rows)))
        return ShellEval(value=value, grad=grad, hess=hess, penalty_factor=None, terms={})


def _factor_g(problem: ShellProblem) -> sp.csr_matrix | None:
    """G = sqrt(2 k_P) (H kron I3), or None without penalty."""
    if problem.H is None or problem.params.k_P == 0:
        return None
    op = PenaltyOperator.from_matrix(problem.H, problem.topology.n_vertices)
    return penalty_factor(op, problem.params.k_P)


@dataclass(frozen=True, eq=False)
class _Coo:
    """COO pattern of this rank's rows of the augmented matrix and its constant values.

    ``rows``/``cols`` are PETSc indices; the first ``n_hess`` entries take the Hessian rows'
    data (in CSR order), the rest are the constant G, G^T and -I entries ``fixed``.
    """

    rows: np.ndarray
    cols: np.ndarray
    n_hess: int
    fixed: np.ndarray
    diag: np.ndarray


def _dof_index(layout: SplitLayout, vertices: np.ndarray) -> np.ndarray:
    """PETSc index of every dof (3 per vertex) of ``vertices``, vertex-major."""
    return (layout.vertex_index[vertices][:, None] + np.arange(3)).reshape(-1)


def _penalty_entries(layout: SplitLayout, g: sp.csr_matrix, owned_dofs: np.ndarray,
                     rank: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, cols, values) of G (owned multiplier rows), G^T (owned dof rows) and -I."""
    n_dof = g.shape[1]
    mult_index = (layout.cluster_index[:, None] + np.arange(3)).reshape(-1)
    dof_index = (layout.vertex_index[:, None] + np.arange(3)).reshape(-1)
    coo = g.tocoo()
    mine_g = layout.cluster_rank[coo.row // 3] == rank
    is_owned = np.zeros(n_dof, dtype=bool)
    is_owned[owned_dofs] = True
    mine_gt = is_owned[coo.col]
    mults = mult_index[np.flatnonzero(layout.cluster_rank.repeat(3) == rank)]
    rows = np.concatenate([mult_index[coo.row[mine_g]], dof_index[coo.col[mine_gt]], mults])
    cols = np.concatenate([dof_index[coo.col[mine_g]], mult_index[coo.row[mine_gt]], mults])
    vals = np.concatenate([coo.data[mine_g], coo.data[mine_gt], -np.ones(mults.size)])
    return rows, cols, vals


def _coo_pattern(energy: SplitShellEnergy, hess_rows: sp.csr_matrix,
                 g: sp.csr_matrix | None) -> _Coo:
    """COO entries of this rank: Hessian rows (local columns mapped to PETSc), G, G^T, -I."""
    layout, patch = energy.layout, energy.patch
    row_dofs = _dof_index(layout, patch.interior)
    col_dofs = _dof_index(layout, patch.local)
    counts = np.diff(hess_rows.indptr)
    rows = np.repeat(row_dofs, counts)
    cols = col_dofs[hess_rows.indices]
    diag = np.flatnonzero(rows == cols)
    if g is None:
        return _Coo(rows, cols, rows.size, np.zeros(0), diag)
    p_rows, p_cols, p_vals = _penalty_entries(layout, g, energy.owned_dofs, energy.comm.rank)
    return _Coo(np.concatenate([rows, p_rows]), np.concatenate([cols, p_cols]), rows.size,
                p_vals, diag)


def _owned_rows(ev: Any, caller: str) -> OwnedRows:
    """Return the split energy's Hessian rows of ``ev`` (InputError naming ``caller`` if not)."""
    if not isinstance(ev.hess, OwnedRows):
        raise InputError(f"SplitAugmentedSystem.{caller}: expected the split energy's owned "
                         "Hessian rows")
    return ev.hess


class SplitAugmentedSystem:
    """The distributed augmented Newton system (the ShellNewtonSolver linear interface).

    Args:
        energy: The split energy (gives the layout and the local rows).
        g: The penalty factor G (None without penalty: then the system is just A).
        options: MUMPS options; ``symmetric`` "ldlt" (default of the split solve) or "lu".

    """

    def __init__(self, energy: SplitShellEnergy, g: sp.csr_matrix | None,
                 options: LinearSolverOptions) -> None:
        if options.backend != "mumps" or options.symmetric == "cholesky":
            raise InputError("LinearSolverOptions: the split augmented solve needs backend "
                             f"'mumps' with 'ldlt' or 'lu', got {options.backend}/"
                             f"{options.symmetric}")
        begin_petsc_log()  # symbolic factorisations are counted from PETSc's log events
        self.energy, self.g, self.options = energy, g, options
        self.expected_negative = 0 if g is None else g.shape[0]
        self.mat: Any = None
        self.local_nnz = 0
        self.analyses = 0
        self.memory_mb = (0.0, 0.0)  # MUMPS INFOG(21) max per rank, INFOG(22) sum, in MB
        self._times = [0.0, 0.0, 0.0]  # factorise, analysis, solve

    def _setup(self, hess_rows: sp.csr_matrix) -> None:
        """COO preallocation of this rank's rows, vectors and the KSP (once)."""
        self._coo = _coo_pattern(self.energy, hess_rows, self.g)
        offsets = self.energy.layout.offsets
        r = self.energy.comm.rank
        local, total = int(offsets[r + 1] - offsets[r]), int(offsets[-1])
        mat = coo_aij(self.energy.comm, local, total, self._coo.rows, self._coo.cols)
        self.mat, self.local_nnz = mat, int(self._coo.rows.size)
        self._values = np.zeros(self._coo.rows.size, dtype=PETSc.ScalarType)
        self._values[self._coo.n_hess:] = self._coo.fixed
        self.ksp = self._create_ksp()
        self.rhs, self.sol = mat.createVecs()

    def _create_ksp(self) -> Any:
        """KSPPREONLY + PCFactor(MUMPS), controls set on the factor matrix.

        ICNTL(13) = 1: no ScaLAPACK on the root front, whose pivots INFOG(12) would not count
        (the inertia test would miss negative eigenvalues on more than one rank).
        """
        return factor_ksp(self.mat, self.options, self.energy.comm, mumps_icntl=((13, 1),))

    def factorize(self, ev: Any, tau: float) -> FactorReport:
        """Insert this rank's rows of the augmented matrix with ``A + tau I``; factorise."""
        hess = _owned_rows(ev, "factorize")
        if self.mat is None:
            self._setup(hess.matrix)
        n_hess = self._coo.n_hess
        self._values[:n_hess] = hess.matrix.data
        self._values[self._coo.diag] += tau
        self.mat.setValuesCOO(self._values)
        return self._factor(tau)

    def _symbolic_count(self) -> int:
        """Symbolic factorisations logged by PETSc so far."""
        return int(factor_event_totals(self.options.symmetric)[0][1])

    def _factor(self, tau: float) -> FactorReport:
        """PCSetUp (numeric, symbolic the first time); MUMPS INFOG(1) / INFOG(12)."""
        pc, before = self.ksp.getPC(), self._symbolic_count()
        failed, error, elapsed = setup_pc(pc)
        self.analyses += self._symbolic_count() - before
        first = self._times[0] == 0.0
        self._times[0] += elapsed
        self._times[1] += elapsed if first else 0.0
        report = self._report(pc, failed, error, tau, elapsed)
        if not report.success:  # the factor keeps its error flag: start from a fresh KSP
            self.ksp.destroy()
            self.ksp = self._create_ksp()
        return report

    def _report(self, pc: Any, failed: int, error: str, tau: float,
                elapsed: float) -> FactorReport:
        """FactorReport with the inertia count against the 3c expected negative pivots."""
        success, negatives, reason = factor_status(pc, failed, error, self.options)
        if failed != -1:
            factor = pc.getFactorMatrix()
            self.memory_mb = (float(factor.getMumpsInfog(21)), float(factor.getMumpsInfog(22)))
        return FactorReport(success=success, reason=reason, negative_pivots=negatives,
                            expected_negative=self.expected_negative, numeric_time=elapsed,
                            shift=float(tau))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``dx`` (3n,) on every rank from the full right-hand side ``rhs`` (3n,)."""
        start = time.perf_counter()
        owned = self.energy.owned_dofs
        local = np.zeros(self.rhs.getLocalSize())
        local[: owned.size] = rhs[owned]
        self.rhs.setArray(local)
        self.ksp.solve(self.rhs, self.sol)
        dx = self.energy.allgather_owned(self.sol.getArray()[: owned.size])
        self._times[2] += time.perf_counter() - start
        return dx

    def times(self) -> tuple[float, float, float]:
        """Accumulated (factorise, first factorisation incl. analysis, solve) seconds."""
        return self._times[0], self._times[1], self._times[2]

    def hessian_product(self, ev: Any, v: np.ndarray) -> np.ndarray:
        """Return ``(A + G^T G) v`` (3n,) on every rank: this rank's rows of A, allgathered.

        The full Hessian of the serial solve (its ``shifted_product`` at ``tau = 0``), for the
        shift ladder's Lanczos restart; ``v`` (3n,) is the same on every rank.
        """
        hess = _owned_rows(ev, "hessian_product")
        local = np.asarray(v, dtype=np.float64).reshape(-1, 3)[self.energy.patch.local]
        out = self.energy.allgather_owned(hess.matrix @ local.reshape(-1))
        if self.g is not None:
            out += self.g.T @ (self.g @ v)
        return out


@dataclass(frozen=True)
class SplitInfo:
    """What the split solve distributed (this rank's view).

    Attributes:
        owned_vertices: Vertices owned by this rank.
        local_vertices: Vertices this rank's stencils read (owned + halo).
        local_matrix_entries: Entries of the augmented matrix stored on this rank (its rows).
        global_size: Rows of the augmented matrix (3n + 3c).
        symbolic_analyses: Symbolic factorisations during the solve (1 = analysis reused).
        factor_memory_mb: MUMPS memory of the last factorisation (INFOG(21): largest rank,
            INFOG(22): all ranks), MB.

    """

    owned_vertices: int
    local_vertices: int
    local_matrix_entries: int
    global_size: int
    symbolic_analyses: int
    factor_memory_mb: tuple[float, float] = (0.0, 0.0)


class SplitNewtonSolver:
    """Monolithic Newton split by stencils over ``comm`` (see the module docstring).

    Build once per problem; :meth:`minimize` may be called for several frames (new targets
    through :meth:`set_target`), reusing the symbolic analysis. ``options.linear_method``
    picks the distributed Newton system: "direct", the augmented MUMPS LDL^T above
    (``options.augmented_linear``), or "multigrid", CG with the distributed geometric
    multigrid of :mod:`.split_multigrid` (``options.multigrid``; needs ``prolongations``).
    The shift ladder's Lanczos restart (``inertia_restart``, direct path) runs on the
    distributed product :meth:`SplitAugmentedSystem.hessian_product`.

    Args:
        problem: The global shell problem (the same on every rank).
        partition: (n,) cluster partition used for the ownership (None: index ranges).
        options: Newton options.
        comm: Communicator (default COMM_WORLD).
        prolongations: The subdivision hierarchy's ``P_l``, coarse to fine (multigrid).

    """

    def __init__(self, problem: ShellProblem, partition: np.ndarray | None = None,
                 options: ShellNewtonOptions | None = None, comm: Any = None,
                 prolongations: tuple[sp.csr_matrix, ...] | None = None) -> None:
        self.comm = comm if comm is not None else MPI.COMM_WORLD
        options = options or ShellNewtonOptions()
        vertex_rank = rank_of_vertices(problem, partition, self.comm.size)
        g = _factor_g(problem)
        h = sp.csr_matrix(problem.H) if g is not None else None
        self.layout = SplitLayout.build(vertex_rank, h, self.comm.size)
        self.energy = SplitShellEnergy(problem, self.layout, self.comm)
        self.newton = ShellNewtonSolver(
            self.energy,  # type: ignore[arg-type]
            replace(options, linear_method="direct"))
        self.linear: SplitAugmentedSystem | SplitMultigridSystem
        if options.linear_method == "multigrid":
            if prolongations is None:
                raise InputError("SplitNewtonSolver: linear_method 'multigrid' needs the "
                                 "subdivision hierarchy (prolongations=)")
            self.linear = SplitMultigridSystem(
                self.energy, prolongations, g, self.layout.cluster_rank, options.multigrid,
                geometry=(problem.rest.positions, problem.topology.faces))
            self.newton.krylov = self.linear
        else:
            self.linear = SplitAugmentedSystem(self.energy, g, options.augmented_linear)
            self.newton.hessian_product = self.linear.hessian_product
        self.newton.linear = self.linear
        self._method = options.linear_method

    @property
    def options(self) -> ShellNewtonOptions:
        """The Newton options in use (``linear_method`` as given)."""
        return replace(self.newton.options, linear_method=self._method)

    @options.setter
    def options(self, value: ShellNewtonOptions) -> None:
        self._method = value.linear_method
        self.newton.options = replace(value, linear_method="direct")

    @property
    def shift_state(self) -> np.ndarray:
        """The Newton's shift memory across solves (:attr:`ShellNewtonSolver.shift_state`)."""
        return self.newton.shift_state

    @shift_state.setter
    def shift_state(self, value: np.ndarray) -> None:
        self.newton.shift_state = value

    def set_target(self, y: np.ndarray) -> None:
        """Set a new penalty target (n, 3) for the next frame (the same on every rank)."""
        self.energy.set_target(y)

    def set_hinge_branch(self, branch: np.ndarray | None) -> None:
        """Set the hinges' reference angles (global, Hn) of this rank's local energy.

        As :meth:`models.shell.energy.ShellEnergy.set_hinge_branch` on the whole shell (the
        same array on every rank).
        """
        self.energy.patch.set_hinge_branch(branch)

    def use_phase_space(self, active: bool) -> None:
        """As :meth:`ShellNewtonSolver.use_phase_space` (the distributed multigrid's space)."""
        self.newton.use_phase_space(active)

    @property
    def phase_space_in_use(self) -> bool:
        """As :attr:`ShellNewtonSolver.phase_space_in_use`."""
        return self.newton.phase_space_in_use

    def minimize(self, x0: np.ndarray) -> tuple[np.ndarray, ShellSolveReport]:
        """Newton from ``x0`` (n, 3, the same on every rank); x identical on every rank."""
        return self.newton.minimize(np.asarray(x0, dtype=np.float64))

    def info(self) -> SplitInfo:
        """Sizes of this rank's share (after at least one factorisation; direct solve)."""
        linear = self.linear
        if not isinstance(linear, SplitAugmentedSystem):
            raise InputError("SplitNewtonSolver.info: only for the direct (augmented) solve")
        return SplitInfo(owned_vertices=self.energy.patch.n_vertices,
                         local_vertices=int(self.energy.patch.local.size),
                         local_matrix_entries=linear.local_nnz,
                         global_size=int(self.layout.offsets[-1]),
                         symbolic_analyses=linear.analyses,
                         factor_memory_mb=linear.memory_mb)


def split_minimize(problem: ShellProblem, x0: np.ndarray, partition: np.ndarray | None = None,
                   options: ShellNewtonOptions | None = None,
                   comm: Any = None) -> tuple[np.ndarray, ShellSolveReport]:
    """One-shot :class:`SplitNewtonSolver` solve; ``(x, report)`` identical on every rank."""
    return SplitNewtonSolver(problem, partition, options, comm).minimize(x0)
