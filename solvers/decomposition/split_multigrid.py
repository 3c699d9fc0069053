r"""Multigrid-preconditioned CG on the split layout: the distributed multigrid Newton system.

The distributed counterpart of :class:`solvers.multigrid.MultigridLinearSystem` for
:class:`~solvers.decomposition.split_newton.SplitNewtonSolver`: every rank holds the rows of
its own vertices on every level and PETSc does the products and the messages.

* Ownership per level: the finest level's vertices belong to the ranks of the split layout; a
  coarser vertex ``j`` of level ``l`` belongs to the owner of the level-``l+1`` vertex with
  the largest weight in column ``j`` of ``S_l`` (for the linear and Loop schemes, the vertex
  at the same place), so a prolongation row and most of its columns live on one rank.
  PETSc numbers each level rank by rank (dof ``3 v + k`` of rank r's ``i``-th vertex is
  ``offset_r + 3 i + k``).
* Fine level: ``A + tau I`` from the split energy's owned Hessian rows as their upper block
  triangle (``MATMPISBAIJ``, 3 x 3 blocks, :class:`solvers.shared_aij.BlockUpperCopy`) for
  the CG and smoother products (half the bytes of the full rows). The level below it is
  summed over 3 x 3 blocks from every rank's rows (:class:`.split_galerkin.SplitGalerkin`:
  no fine AIJ, no stored ``A P``); the coarser ``A_l = P_l^T A_{l+1} P_l`` by PETSc's
  parallel ``MatPtAP`` (symbolic product reused), ``P_l = S_l (x) I_3`` as ``MATMPIAIJ``.
* Penalty: as in the serial solver, ``G^T G`` (``G = sqrt(2 k_P) H (x) I_3``) is never
  assembled on the fine levels: level ``l`` applies ``A_l + G_l^T G_l`` matrix-free
  (``G_l = G_{l+1} P_l``, rows owned by the cluster's owner), Jacobi reads
  ``diag(A_l) + colsum(G_l .* G_l)``, and the coarsest level ``A_0 + G_0^T G_0`` is
  assembled and factorised by MUMPS Cholesky on all ranks, or applied as one GAMG cycle over
  the ranks when it is large (:func:`solvers.multigrid.coarse_by_amg`).
* CG (unpreconditioned norm) with Chebyshev/Jacobi smoothing (Briggs, Henson & McCormick, A
  Multigrid Tutorial, ch. 3), the forcing term of :func:`solvers.multigrid.forcing_term`
  (Eisenstat & Walker 1996, choice 2) and the true relative residual as acceptance test.
  A CG that fails (negative curvature, an indefinite coarse matrix) returns NaN, and the
  shell Newton moves to its next shift. The Chebyshev bounds are estimated at every set-up,
  or with ``eigen_estimate = "solve"`` once per Newton solve (Jacobi diagonals refreshed at
  every set-up; a failed CG with bounds from an earlier Newton iteration gets new ones and
  is repeated unless it met negative curvature), as in the serial solver.
* With ``options.phase_space`` the wrinkle-phase coarse space of :mod:`.split_phase` deflates
  CG (A-DEF2 around the V-cycle, from ``x_0 = Q b``), as in the serial solver (its ``Z^T A Z``
  from the rank's Hessian rows themselves); with an indefinite ``Z^T A Z`` that matrix's CG
  runs without the correction.

The PCMG set-up, Galerkin levels and deflated CG are the serial solver's own functions; its
coarse SBAIJ copies, threads and direct fallback have no distributed form (one rank: serial).
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import PETSc
from solvers.decomposition.split_galerkin import SplitGalerkin
from solvers.decomposition.split_phase import SplitPhaseSpace
from solvers.linear import FactorReport
from solvers.multigrid import (
    JacobiPC,
    KrylovBase,
    LowRankOperator,
    MultigridOptions,
    galerkin_levels,
    gram_diagonal,
    multigrid_cg,
    penalty_levels,
    shift_images,
)
from solvers.phase_space import deflated_cg, hat_matrix
from solvers.shared_aij import BlockUpperCopy


def level_owners(fine_owner: np.ndarray, prolongations: tuple[sp.csr_matrix, ...]
                 ) -> list[np.ndarray]:
    """Owning rank of every vertex of every level, coarse to fine (the last is ``fine_owner``).

    Coarse vertex ``j`` goes to the owner of the finer vertex with the largest ``|S_ij|``
    (``S_l`` is read off the dof prolongation ``P_l = S_l (x) I_3`` as its ``[::3, ::3]``).
    """
    owners = [np.asarray(fine_owner, dtype=np.int64)]
    for p in reversed(prolongations):
        s = sp.csc_matrix(abs(p[::3, ::3]))
        counts = np.diff(s.indptr)
        if np.any(counts == 0):
            raise InputError("level_owners: a coarse vertex has no finer vertex (column of S_l "
                             "empty)")
        heaviest = np.maximum.reduceat(s.data, s.indptr[:-1])
        hits = np.flatnonzero(s.data == np.repeat(heaviest, counts))
        first = hits[np.searchsorted(hits, s.indptr[:-1])]  # the first heaviest per column
        owners.append(owners[-1][s.indices[first]])
    return owners[::-1]


@dataclass(frozen=True, eq=False)
class LevelNumbering:
    """PETSc numbering of one level's dofs, rank by rank.

    Attributes:
        owner: (n,) rank of every vertex.
        dof: (3n,) PETSc index of every dof ``3 v + k``.
        offsets: (size + 1,) PETSc row ranges of the ranks.
        owned: (3 n_r,) dofs (``3 v + k``) of this rank in its PETSc row order.

    """

    owner: np.ndarray
    dof: np.ndarray
    offsets: np.ndarray
    owned: np.ndarray

    @classmethod
    def build(cls, owner: np.ndarray, rank: int, size: int) -> LevelNumbering:
        """Build the numbering by (owner, index); 3 consecutive dofs per vertex."""
        counts = np.bincount(owner, minlength=size)
        offsets = np.concatenate([[0], np.cumsum(3 * counts)]).astype(np.int64)
        order = np.argsort(owner, kind="stable")
        vertex = np.empty(owner.size, dtype=np.int64)
        vertex[order] = 3 * np.arange(owner.size)
        dof = (vertex[:, None] + np.arange(3)).reshape(-1)
        mine = np.flatnonzero(owner == rank)
        return cls(owner, dof, offsets, (3 * mine[:, None] + np.arange(3)).reshape(-1))

    @property
    def local_size(self) -> int:
        """Rows of this rank."""
        return int(self.owned.size)

    @property
    def size(self) -> int:
        """Rows of the level."""
        return int(self.offsets[-1])


def _owned_aij(comm: Any, m: sp.csr_matrix, rows: LevelNumbering,
               cols: LevelNumbering) -> Any:
    """``m``'s rows owned here (``rows.owned``, PETSc order) as an assembled ``MATMPIAIJ``.

    Columns are mapped to PETSc's numbering (``cols.dof``). Built from CSR
    (``MatMPIAIJSetPreallocationCSR``): a matrix set once keeps no per-entry maps
    (``MatSetPreallocationCOO`` would keep two 8-byte integers per entry).
    """
    local = sp.csr_matrix(m[rows.owned])
    local = sp.csr_matrix((local.data, cols.dof[local.indices], local.indptr),
                          shape=(rows.local_size, cols.size))
    local.sum_duplicates()  # sorts each row's PETSc columns
    mat: Any = PETSc.Mat().createAIJ(
        ((rows.local_size, rows.size), (cols.local_size, cols.size)),
        csr=(local.indptr.astype(PETSc.IntType), local.indices.astype(PETSc.IntType),
             local.data.astype(PETSc.ScalarType)), comm=comm)
    mat.assemble()
    return mat


class SplitMultigridSystem(KrylovBase):
    """CG + PCMG for ``(A + tau I + G^T G) dx = b`` over ``comm`` (module docstring).

    The Newton-system interface of :class:`~solvers.shell_newton.ShellNewtonSolver`
    (``factorize(ev, tau)``, ``solve(b)``, ``times()``) plus the forcing-term calls it makes
    on a Krylov solver (``reset_forcing``, ``set_gradient_norm``, ``stats``).

    Args:
        energy: The split energy (owned Hessian rows, the allgather of owned values).
        prolongations: ``P_l`` coarse to fine (:meth:`solvers.multigrid.ShellHierarchy.
            prolongations`), the last ending at the shell's dofs.
        g: The penalty factor G (3c x 3n; None without penalty), the same on every rank.
        cluster_rank: (c,) rank owning each penalty row (the split layout's).
        options: CG / multigrid options (see the module docstring for those that apply).
        geometry: Rest vertices and faces of the shell (``options.phase_space`` needs them).

    """

    def __init__(self, energy: Any, prolongations: tuple[sp.csr_matrix, ...],
                 g: sp.csr_matrix | None, cluster_rank: np.ndarray,
                 options: MultigridOptions,
                 geometry: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        if not prolongations:
            raise InputError("SplitMultigridSystem: the hierarchy needs >= 1 subdivision level")
        if options.smoother_pc != "jacobi":
            raise InputError(f"MultigridOptions.smoother_pc: {options.smoother_pc!r} has no "
                             "distributed form (PETSc's parallel SOR takes no 3 x 3 blocks "
                             "of the fine SBAIJ level); use 'jacobi' on more than one rank")
        super().__init__(options)
        self.energy, self.comm = energy, energy.comm
        rank, size = self.comm.rank, self.comm.size
        owners = level_owners(energy.layout.vertex_rank, prolongations)
        self.levels = [LevelNumbering.build(o, rank, size) for o in owners]
        fine = self.levels[-1]
        if not np.array_equal(fine.owned, energy.owned_dofs):
            raise InputError("SplitMultigridSystem: the split energy's owned dofs are not in "
                             "rank-by-rank vertex order")
        self.p_mats = [self._prolongation(p, self.levels[i + 1], self.levels[i])
                       for i, p in enumerate(prolongations)]
        self._penalty, self._coarse_penalty = self._penalty_levels(g, prolongations,
                                                                   cluster_rank)
        self._finest, self._fine_products = self._fine_matrices(prolongations[-1])
        self._galerkin: list[Any] = []
        self._images = [_owned_aij(self.comm, m, level, level) for m, level in
                        zip(shift_images(prolongations), self.levels[:-1], strict=True)]
        self._levels_shift = 0.0
        self._coarse: Any = None
        self._ksp: Any = None
        self._vecs: tuple[Any, Any, Any] | None = None
        self._current: weakref.ref[Any] | None = None
        self.phase = self._phase_space(prolongations, geometry)
        self._phase_ready = False
        self._deflated: Any = None
        self._jacobi: list[JacobiPC] = []

    def _phase_space(self, prolongations: tuple[sp.csr_matrix, ...],
                     geometry: tuple[np.ndarray, np.ndarray] | None) -> SplitPhaseSpace | None:
        """Build the distributed wrinkle-phase space when ``options.phase_space`` (else None)."""
        if not self.options.phase_space:
            return None
        if geometry is None:
            raise InputError("MultigridOptions.phase_space: needs the shell's rest geometry "
                             "(SplitMultigridSystem(..., geometry=(vertices, faces)))")
        level = self.options.phase_level
        hats = hat_matrix(tuple(sp.csr_matrix(p[::3, ::3]) for p in prolongations), level)
        fine, columns = self.levels[-1], self.levels[level]
        return SplitPhaseSpace(*geometry, hats,
                               (self.energy.patch.local, (fine.local_size, fine.size)),
                               (columns.dof, (columns.local_size, columns.size)), self.comm,
                               self.options.threads)

    def _prolongation(self, p: sp.csr_matrix, fine: LevelNumbering,
                      coarse: LevelNumbering) -> Any:
        """``P_l`` as ``MATMPIAIJ`` (rows of the fine level, columns of the coarse)."""
        return _owned_aij(self.comm, sp.csr_matrix(p), fine, coarse)

    def _penalty_levels(self, g: sp.csr_matrix | None, prolongations: tuple[sp.csr_matrix, ...],
                        cluster_rank: np.ndarray
                        ) -> tuple[list[tuple[Any, np.ndarray] | None], Any]:
        """Return the distributed penalty of every level and of the coarse matrix.

        Per level (coarse to fine) ``(G_l as MATMPIAIJ, owned colsum(G_l .* G_l))``, then
        ``G_0^T G_0`` as MATMPIAIJ (both None without penalty).
        """
        if g is None:
            return [None] * len(self.levels), None
        chain = [sp.csr_matrix(m) for m in penalty_levels(g, prolongations)]
        rows = LevelNumbering.build(np.asarray(cluster_rank, dtype=np.int64),
                                    self.comm.rank, self.comm.size)
        out: list[tuple[Any, np.ndarray] | None] = []
        for level, gl in zip(self.levels, chain, strict=True):
            mat = _owned_aij(self.comm, gl, rows, level)
            out.append((mat, gram_diagonal(gl)[level.owned]))
        g0, coarse = chain[0], self.levels[0]
        return out, _owned_aij(self.comm, sp.csr_matrix(g0.T @ g0), coarse, coarse)

    # ----------------------------------------------------------------------------- set-up

    def _fine_matrices(self, p: sp.csr_matrix) -> tuple[SplitGalerkin, BlockUpperCopy]:
        """Build the owned Hessian rows' products: the level below, and the fine level's.

        The Galerkin product onto the next coarser level (:class:`SplitGalerkin`, ``p`` its
        prolongation) and the rows' upper block triangle (:class:`BlockUpperCopy`) for the
        fine level's CG and smoother products. Built with the solver, before any frame:
        their set-up arrays are gone before the evaluations and products of a Newton step
        need memory.
        """
        patch, fine, coarse = self.energy.patch, self.levels[-1], self.levels[-2]
        indptr, indices = self.energy.hessian_rows_pattern()
        rows = np.repeat(np.arange(indptr.size - 1, dtype=np.int32), np.diff(indptr))
        if np.count_nonzero(indices == rows) != fine.local_size:  # local dof i is row i
            raise InputError("SplitMultigridSystem: the Hessian rows must contain the diagonal")
        local_dofs = (3 * patch.local[:, None] + np.arange(3)).reshape(-1)
        cols = fine.dof[local_dofs].astype(PETSc.IntType)[indices]
        finest = SplitGalerkin(self.comm, indptr, indices, patch.local,
                               sp.csr_matrix(p[::3, ::3]), coarse.owner, coarse.dof,
                               coarse.offsets, self.options.threads)
        return finest, BlockUpperCopy(self.comm, fine.local_size, fine.size, indptr, cols)

    def factorize(self, ev: Any, tau: float) -> FactorReport:
        """Set the preconditioner up for ``ev.hess + tau I (+ G^T G)`` (collective)."""
        start = time.perf_counter()
        rows = getattr(ev.hess, "matrix", None)
        if rows is None:
            raise InputError("SplitMultigridSystem.factorize: expected the split energy's "
                             "owned Hessian rows")
        self._fine_products.set_values(rows.data, tau)
        same_matrix = self._current is not None and self._current() is ev
        self._current = weakref.ref(ev)  # identity only: the Newton frees an old Hessian
        phase = self._update_phase(rows, tau, same_matrix)
        if phase is not None and phase.indefinite:
            self.stats.indefinite_skips += 1
        self._galerkin_products(rows, tau, new_matrix=not same_matrix)
        self._finish_setup()
        return self._setup_done(start, FactorReport(success=True, shift=float(tau)))

    def _galerkin_products(self, rows: sp.csr_matrix, tau: float, new_matrix: bool) -> None:
        """Compute the levels below the fine one, or shift the last ones to ``tau``.

        The level below the fine one from the Hessian ``rows`` (:class:`SplitGalerkin`), the
        coarser ones by PETSc's ``MatPtAP``.

        For the last set-up's matrix with another shift: the change of shift times the
        identity's Galerkin image ``M_l`` (:func:`solvers.multigrid.shift_images`) added to
        each level, whose pattern contains it (exact, no new products).
        """
        if not new_matrix and self._galerkin:
            step = tau - self._levels_shift
            if step:
                for mat, image in zip(self._galerkin, self._images, strict=True):
                    mat.axpy(step, image, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        else:
            below = self._finest.update(rows.data, tau)
            self._galerkin = galerkin_levels(below, self.p_mats[:-1], self._galerkin)
        self._levels_shift = tau

    def _finish_setup(self) -> None:
        """Coarse matrix, smoothers and the KSPs on the current levels (collective)."""
        self._update_coarse()
        if self._ksp is None:
            self._ksp = self._create_ksp()
        for jacobi in self._jacobi:
            jacobi.refresh()
        if self._estimate_due:
            self.renew_bounds()
            self._estimate_due = self.options.eigen_estimate == "setup"
        self._ksp.setUp()
        if self.phase is not None and self._deflated is None:
            self._deflated = self._deflated_ksp()

    def _update_phase(self, rows: sp.csr_matrix, tau: float,
                      same_matrix: bool) -> FactorReport | None:
        """Phase space: new test fields, ``A_Z`` and its factorisation (None: off).

        As :meth:`solvers.multigrid.MultigridLinearSystem._update_phase`: a retry of the same
        evaluation with another shift and unchanged fields only shifts ``A_Z``. ``rows``:
        this rank's rows of the Newton matrix (local columns), without the shift ``tau``.
        """
        self._phase_ready = False
        if self.phase is None or not self.phase_active:
            return None
        penalty = self._penalty[-1]
        report = self.phase.refresh(rows, None if penalty is None else penalty[0], tau,
                                    self._state, same_matrix and not self._fields_stale)
        self._fields_stale = False
        self._phase_ready = report.usable_spd
        return report

    def _deflated_ksp(self) -> Any:
        """CG from ``x_0 = Q b`` preconditioned by A-DEF2 around PCMG (phase space only)."""
        assert self.phase is not None  # only with the phase space (internal invariant)
        return deflated_cg(self.comm, self._operators[-1], self._ksp.getPC(), self.phase)

    def _update_coarse(self) -> None:
        """``A_0 + G_0^T G_0`` into one matrix of fixed pattern (their union)."""
        a0 = self._galerkin[0]
        if self._coarse is None:
            self._coarse = a0.duplicate(copy=True)
            if self._coarse_penalty is not None:
                self._coarse.axpy(1.0, self._coarse_penalty,
                                  PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
            self._coarse.setOption(PETSc.Mat.Option.SYMMETRIC, True)
            return
        self._coarse.zeroEntries()
        self._coarse.axpy(1.0, a0, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        if self._coarse_penalty is not None:
            self._coarse.axpy(1.0, self._coarse_penalty,
                              PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)

    def _level_operator(self, level: int) -> Any:
        """Level ``level`` (>= 1) as a ``MatPython``: ``A_l + G_l^T G_l``."""
        numbering, penalty = self.levels[level], self._penalty[level]
        fine = level == len(self.levels) - 1  # its products read the upper block triangle
        a = self._fine_products.mat if fine else self._galerkin[level]
        context = LowRankOperator.of_petsc(a, *(penalty or (None, 0.0)))
        sizes = (numbering.local_size, numbering.size)
        mat: Any = PETSc.Mat().createPython((sizes, sizes), context, comm=self.comm)
        mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        mat.setUp()
        return mat

    def _create_ksp(self) -> Any:
        """CG (unpreconditioned norm) + PCMG: Chebyshev/Jacobi levels, MUMPS coarse."""
        self._operators = [self._level_operator(level) for level in range(1, len(self.levels))]
        levels = [self._coarse, *self._operators]
        ksp, self._jacobi = multigrid_cg(self.comm, levels, levels, self.p_mats,
                                         self.options, f"wrinkles_split_mg{id(self)}_")
        b, x = self._operators[-1].createVecs()
        self._vecs = (b, x, b.duplicate())  # right-hand side, solution, residual
        return ksp

    # ----------------------------------------------------------------------------- solve

    @property
    def fine_matrix(self) -> Any:
        """The fine level's ``A + tau I`` of the last set-up (``MATMPISBAIJ``, owned rows)."""
        return self._fine_products.mat

    @property
    def fine_penalty(self) -> Any:
        """The fine level's ``G`` (``MATMPIAIJ``, rows by cluster owner), None without."""
        penalty = self._penalty[-1]
        return None if penalty is None else penalty[0]

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """Return one V-cycle (PCMG from zero) applied to this rank's rows ``r`` (collective).

        The cycle is symmetric, as the serial one (:meth:`solvers.multigrid.
        MultigridLinearSystem.precondition`): it preconditions an outer CG
        (:mod:`.split_coupled`). ``r`` and the result: owned fine dofs, PETSc order.
        """
        assert self._vecs is not None  # factorize() ran first (internal invariant)
        b, x, _ = self._vecs
        b.setArray(np.ascontiguousarray(r, dtype=np.float64))
        self._ksp.getPC().apply(b, x)
        return x.getArray(readonly=True).copy()

    def _failed(self, rhs: np.ndarray) -> np.ndarray:
        """Return NaN (a failed direction: the shell Newton moves to its next shift)."""
        return np.full(3 * self.energy.n_vertices, np.nan)

    def _accepted_cg(self, rhs: np.ndarray) -> np.ndarray | None:
        """CG from 0 (from ``Q b`` with the phase space); ``dx`` if the true residual passes."""
        assert self._vecs is not None  # factorize() ran first (internal invariant)
        b, x, r = self._vecs
        b.setArray(np.ascontiguousarray(rhs[self.levels[-1].owned], dtype=np.float64))
        x.set(0.0)
        ksp = self._deflated if self._phase_ready else self._ksp
        if self._phase_ready:
            ksp.getPC().getPythonContext().start(b, x)
        ksp.setTolerances(rtol=self.eta, atol=0.0, max_it=self.options.max_iterations)
        ksp.solve(b, x)
        self.stats.iterations.append(int(ksp.getIterationNumber()))
        reason = ksp.getConvergedReason()
        self.negative_curvature = reason == PETSc.KSP.ConvergedReason.DIVERGED_INDEFINITE_MAT
        if reason <= 0:
            return None
        self._operators[-1].mult(x, r)
        r.aypx(-1.0, b)
        residual = r.norm() / (b.norm() or 1.0)
        if residual > self.options.residual_slack * self.eta:
            return None
        self.stats.true_residuals.append(float(residual))
        return self.energy.allgather_owned(x.getArray(readonly=True))

    def times(self) -> tuple[float, float, float]:
        """Return (set-up, analysis, CG solve) seconds."""
        return self.stats.setup_time, 0.0, self.stats.solve_time


__all__ = ["LevelNumbering", "SplitMultigridSystem", "level_owners"]
