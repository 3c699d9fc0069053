"""Geometric multigrid on the subdivision hierarchy: preconditioned CG for the shell Newton system.

The shell is the coarse surface subdivided ``L`` times (:mod:`models.embedding.subdivision`),
``V_{l+1} = S_l V_l``; those matrices are the prolongations of a geometric multigrid (Briggs,
Henson & McCormick, A Multigrid Tutorial, 2nd ed., ch. 3 and 8). On the flat dof vector
(dof ``3 i + k``) ``P_l = S_l (x) I_3`` and the level operators are Galerkin products

    A_l = P_l^T A_{l+1} P_l            (over 3 x 3 vertex blocks, :mod:`solvers.block_galerkin`;
                                        the distributed solver: PETSc MatPtAP),

so the two-grid error propagation ``(I - P A_c^{-1} P^T A)`` is an A-orthogonal projection;
linear subdivision reproduces the rigid and uniform-stretch modes exactly.

The penalty enters as the low-rank ``G^T G`` (``G = sqrt(2 k_P) H (x) I_3``,
:mod:`models.shell.penalty`) and is never assembled on the fine levels: a level operator is
``A_l + G_l^T G_l`` applied matrix-free (``G_l = G_{l+1} P_l``), with the diagonal
``diag(A_l) + colsum(G_l^2)`` for the Jacobi smoother. The coarsest level ``A_0 + G_0^T G_0``
is assembled and factorised by MUMPS Cholesky (analysis reused).

Smoother: Chebyshev (``smoother_degree``) on Jacobi, bounds ``[0.1, 1.1] lambda_max``
estimated by PETSc (kept for a whole Newton solve with ``eigen_estimate = "solve"``). Krylov
method: CG on the unpreconditioned residual; the true relative residual ``||b - A x|| / ||b||``
is recomputed after the solve and is the acceptance test (MISSION.md section 6). An indefinite
Newton matrix makes CG break down or return a non-descent direction: the solve then falls
back to the direct factorisation (``fallback``), or the shell Newton moves to the next shift.
``level_format = "sbaij"`` multiplies with a symmetric 3 x 3 block copy of ``A_l`` (upper
triangle, about 40 % of the bytes of the AIJ product). Optional wrinkle-phase coarse space:
:mod:`solvers.phase_space`.

Inexact Newton: with ``forcing = "eisenstat_walker"`` the CG tolerance of Newton iteration k is
Eisenstat & Walker's choice 2 (SIAM J. Sci. Comput. 17, 1996, eq. 2.6 with the safeguard of
sec. 3), ``eta_k = gamma (||g_k|| / ||g_{k-1}||)^alpha``, bounded below by
``max(rtol, gamma eta_{k-1}^alpha)`` when that exceeds 0.1 and above by ``eta_max``.

Measured iteration counts and timings, and the options tried and not adopted:
docs/notes/multigrid.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numba
import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import PETSc
from models.embedding.subdivision import Subdivision, SubdivisionOptions, subdivide
from models.shell.schedule import balanced_cuts, check_threads
from solvers.block_galerkin import GalerkinChain
from solvers.linear import MUMPS_ORDERINGS, FactorReport
from solvers.phase_space import (
    PhaseSpace,
    deflated_cg,
    field_state,
    hat_matrix,
    petsc_aij,
    same_state,
)

FORCING: tuple[str, ...] = ("fixed", "eisenstat_walker")
CYCLES: tuple[str, ...] = ("v", "w")
SMOOTHER_PCS: tuple[str, ...] = ("jacobi", "sor")
EIGEN_ESTIMATES: tuple[str, ...] = ("setup", "solve")
LEVEL_FORMATS: tuple[str, ...] = ("aij", "sbaij")


@dataclass(frozen=True)
class MultigridOptions:
    """Options of the multigrid-preconditioned CG solve of the Newton system.

    Attributes:
        rtol: True relative residual ``||b - A x|| / ||b||`` the CG solve must reach (the
            fixed forcing term; the floor of the Eisenstat-Walker one). Dimensionless.
        max_iterations: CG iterations before the solve counts as failed.
        forcing: "fixed" (``rtol`` every Newton iteration) or "eisenstat_walker" (inexact
            Newton, choice 2).
        ew_gamma: Eisenstat-Walker gamma in (0, 1].
        ew_alpha: Eisenstat-Walker exponent alpha in (1, 2].
        ew_max: Largest forcing term eta_max in (0, 1).
        smoother_degree: Chebyshev smoothing steps per level, before and after the coarse
            correction (>= 1).
        smoother_pc: Chebyshev's preconditioner: "jacobi" (diagonal of the level operator,
            penalty included) or "sor" (symmetric SOR on ``A_l`` alone; one rank only).
        cycle: "v" or "w" cycle.
        residual_slack: A solve is accepted when the true relative residual is at most
            ``residual_slack`` times the requested tolerance (>= 1; the recursive CG residual
            drifts from the true one by round-off).
        fallback: On CG failure solve with the direct factorisation instead; False returns
            NaN, a failed direction for the Newton.
        eigen_estimate: When the finest level's Chebyshev bounds ``lambda_max(D^-1 A)`` are
            re-estimated (:meth:`KrylovBase.renew_bounds`): "setup" (every set-up) or
            "solve" (a Newton solve's first; needs ``smoother_pc = "jacobi"``).
        level_format: Level matrices ``A_l`` (l >= 1) in the CG and smoother products: "aij"
            (the Galerkin products) or "sbaij" (a symmetric 3 x 3 block copy, upper triangle).
        target_fraction: When > 0, the CG tolerance of an iteration is at least
            ``min(ew_max, target_fraction tol / ||g_k||)`` for the Newton tolerance ``tol``
            (in [0, 1); 0 = off).
        phase_space: Add the wrinkle-phase coarse space of :mod:`solvers.phase_space` as a
            deflation (A-DEF2) correction around the V-cycle.
        phase_level: Hierarchy level whose vertex hats modulate the test fields (0 = the
            coarse mesh; ``3 n_level`` columns).
        threads: Threads (numba ``prange``) of the "sbaij" level products and the penalty
            products (>= 1; 1 starts no thread pool; keep 1 under MPI, one core per rank).

    """

    rtol: float = 1e-8
    max_iterations: int = 300
    forcing: str = "fixed"
    ew_gamma: float = 0.9
    ew_alpha: float = 0.5 * (1.0 + np.sqrt(5.0))
    ew_max: float = 0.1
    smoother_degree: int = 2
    smoother_pc: str = "jacobi"
    cycle: str = "v"
    residual_slack: float = 10.0
    fallback: bool = True
    eigen_estimate: str = "setup"
    level_format: str = "aij"
    target_fraction: float = 0.0
    phase_space: bool = False
    phase_level: int = 0
    threads: int = 1

    def __post_init__(self) -> None:
        check_threads(self.threads, "MultigridOptions.threads")
        if self.phase_level < 0:
            raise InputError(f"MultigridOptions.phase_level: must be >= 0, got "
                             f"{self.phase_level!r}")
        if not 0 <= self.target_fraction < 1:
            raise InputError(f"MultigridOptions.target_fraction: must be in [0, 1), got "
                             f"{self.target_fraction!r}")
        choices = {"level_format": LEVEL_FORMATS, "eigen_estimate": EIGEN_ESTIMATES,
                   "forcing": FORCING, "smoother_pc": SMOOTHER_PCS, "cycle": CYCLES}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise InputError(f"MultigridOptions.{name}: expected one of {list(allowed)}, "
                                 f"got {getattr(self, name)!r}")
        if self.eigen_estimate == "solve" and self.smoother_pc != "jacobi":
            raise InputError("MultigridOptions.eigen_estimate: 'solve' needs smoother_pc = "
                             "'jacobi' (SOR re-reads the changing A_l)")
        _check_open(self.rtol, 0.0, 1.0, "rtol")
        _check_open(self.ew_max, 0.0, 1.0, "ew_max")
        _check_open(self.ew_gamma, 0.0, 1.0 + 1e-15, "ew_gamma")
        _check_open(self.ew_alpha, 1.0, 2.0 + 1e-15, "ew_alpha")
        for name in ("max_iterations", "smoother_degree"):
            if getattr(self, name) < 1:
                raise InputError(f"MultigridOptions.{name}: must be >= 1, got "
                                 f"{getattr(self, name)!r}")
        if not self.residual_slack >= 1:
            raise InputError(f"MultigridOptions.residual_slack: must be >= 1, got "
                             f"{self.residual_slack!r}")


def _check_open(value: float, low: float, high: float, name: str) -> None:
    """InputError naming ``MultigridOptions.name`` unless ``low < value < high``."""
    if not (np.isfinite(value) and low < value < high):
        raise InputError(f"MultigridOptions.{name}: must be in ({low:g}, {high:g}), got "
                         f"{value!r}")


@dataclass(frozen=True)
class ShellHierarchy:
    """A shell obtained by subdividing a coarse mesh, with the matrices kept for multigrid.

    Attributes:
        subdivision: The :class:`~models.embedding.subdivision.Subdivision` (fine vertices and
            faces, per-level matrices ``S_l`` of shape ``(n_{l+1}, n_l)``).

    """

    subdivision: Subdivision

    @classmethod
    def build(cls, points: np.ndarray, faces: np.ndarray, levels: int,
              scheme: str = "linear") -> ShellHierarchy:
        """Subdivide ``(points, faces)`` ``levels`` times (``scheme`` "linear" or "loop")."""
        opts = SubdivisionOptions(levels=levels, scheme=scheme)  # type: ignore[arg-type]
        return cls(subdivide(points, faces, opts))

    @property
    def vertices(self) -> np.ndarray:
        """Fine (shell) vertices ``(n_L, 3)``."""
        return self.subdivision.vertices

    @property
    def faces(self) -> np.ndarray:
        """Fine (shell) faces ``(m_L, 3)``."""
        return self.subdivision.faces

    @property
    def levels(self) -> int:
        """Number of subdivision levels L (the multigrid has L + 1 levels)."""
        return len(self.subdivision.matrices)

    @property
    def level_sizes(self) -> tuple[int, ...]:
        """Vertices per level, coarse to fine."""
        return (self.subdivision.n_coarse, *(s.shape[0] for s in self.subdivision.matrices))

    def prolongations(self) -> tuple[sp.csr_matrix, ...]:
        """``P_l = S_l (x) I_3`` (``3 n_{l+1} x 3 n_l``), coarse to fine."""
        return tuple(vector_prolongation(s) for s in self.subdivision.matrices)


def vector_prolongation(s: sp.spmatrix) -> sp.csr_matrix:
    """``S (x) I_3``: the vertex matrix S acting on each coordinate of dof ``3 i + k``."""
    return sp.kron(sp.csr_matrix(s), sp.identity(3), format="csr")


def eisenstat_walker(grad_norm: float, previous_norm: float, previous_eta: float,
                     options: MultigridOptions) -> float:
    """Return the forcing term eta_k of Eisenstat & Walker's choice 2, safeguarded.

    Args:
        grad_norm: ``||g_k||``.
        previous_norm: ``||g_{k-1}||`` (0 for the first iteration, which gets ``ew_max``).
        previous_eta: ``eta_{k-1}``.
        options: gamma, alpha, eta_max and the floor ``rtol``.

    """
    if previous_norm <= 0:
        return options.ew_max
    gamma, alpha = options.ew_gamma, options.ew_alpha
    eta = gamma * (grad_norm / previous_norm) ** alpha
    guard = gamma * previous_eta ** alpha
    if guard > 0.1:
        eta = max(eta, guard)
    return float(min(options.ew_max, max(eta, options.rtol)))


def forcing_term(options: MultigridOptions, grad_norm: float, history: tuple[float, float],
                 target: float = 0.0) -> tuple[float, tuple[float, float]]:
    """CG tolerance of a Newton iteration and the new ``(||g||, eta)`` history.

    ``forcing = "fixed"``: ``rtol``; "eisenstat_walker": :func:`eisenstat_walker` from the
    previous iteration's ``history`` (``(0, ew_max)`` at the start of a solve). With
    ``target_fraction`` and the Newton gradient tolerance ``target`` (> 0) the tolerance is
    raised to ``min(ew_max, target_fraction target / ||g_k||)`` when that is larger: the
    linearised gradient after the step, ``||g_k + A dx|| <= eta ||g_k||``, then already lies
    below ``target_fraction`` times the tolerance.
    """
    if options.forcing == "fixed":
        eta = options.rtol
    else:
        eta = eisenstat_walker(grad_norm, history[0], history[1], options)
        history = (grad_norm, eta)
    if options.target_fraction > 0 and target > 0 and grad_norm > 0:
        eta = max(eta, min(options.ew_max, options.target_fraction * target / grad_norm))
    return eta, history


class LowRankOperator:
    """``MatPython`` context of ``A + G^T G`` (A a PETSc matrix, G the penalty factor).

    ``y = A x + G^T (G x)``: ``MatMult`` with A, then the penalty. When ``G = H (x) I_3``
    (every level's factor is: ``G_l = (H S) (x) I_3``) the penalty is two numba passes over
    the vertex-level H and its transpose for all three coordinates (:class:`_VertexPenalty`,
    ``threads`` row ranges each), a third of the entries of the AIJ G; any other G takes
    PETSc's ``MatMult`` / ``MatMultTransposeAdd``. No allocation per call.
    """

    def __init__(self, a: Any, g: sp.csr_matrix | None, threads: int = 1) -> None:
        self.a = a
        self.vertex = None if g is None else _VertexPenalty.of(g, threads)
        self.g = None if g is None or self.vertex is not None else petsc_aij(g)
        self.gx = None if self.g is None else self.g.createVecs()[1]
        self.g_diagonal: np.ndarray | float = 0.0 if g is None else gram_diagonal(g)

    @classmethod
    def of_petsc(cls, a: Any, g: Any, g_diagonal: np.ndarray | float) -> LowRankOperator:
        """Build ``A + G^T G`` from a PETSc G (distributed) and its owned column sums of squares.

        ``g`` None: ``A`` alone. The distributed multigrid's level operators.
        """
        op = cls(a, None)
        op.g, op.g_diagonal = g, g_diagonal
        op.gx = None if g is None else g.createVecs()[1]
        return op

    def mult(self, mat: Any, x: Any, y: Any) -> None:  # noqa: ARG002 (petsc4py signature)
        """``y = A x + G^T (G x)`` (``A x`` without a penalty)."""
        self.a.mult(x, y)
        if self.vertex is not None:
            self.vertex.add(x.getArray(readonly=True), y.getArray())
        elif self.g is not None:
            self.g.mult(x, self.gx)
            self.g.multTransposeAdd(self.gx, y, y)

    def getDiagonal(self, mat: Any, d: Any) -> None:  # noqa: N802, ARG002 (petsc4py names)
        """``d = diag(A) + colsum(G .* G)``."""
        self.a.getDiagonal(d)
        d.getArray()[:] += self.g_diagonal


@dataclass(eq=False)
class _VertexPenalty:
    """``y += G^T (G x)`` for ``G = H (x) I_3`` in two passes over the vertex-level H.

    ``w = H x`` by cluster rows, then ``y += H^T w`` by vertex rows (race-free row ranges,
    one per thread; numba ``prange``).
    """

    h: tuple[np.ndarray, np.ndarray, np.ndarray]
    ht: tuple[np.ndarray, np.ndarray, np.ndarray]
    h_cuts: np.ndarray
    ht_cuts: np.ndarray
    work: np.ndarray

    @classmethod
    def of(cls, g: sp.csr_matrix, threads: int) -> _VertexPenalty | None:
        """Return the vertex-level form of ``g``, or None when ``g`` is not ``H (x) I_3``."""
        h = _vertex_factor(g)
        if h is None:
            return None
        ht = sp.csr_matrix(h.T)
        ht.sort_indices()
        arrays = tuple((m.indptr.astype(np.int64), m.indices.astype(np.int64),
                        m.data.astype(np.float64)) for m in (h, ht))
        return cls(arrays[0], arrays[1], balanced_cuts(arrays[0][0], threads),
                   balanced_cuts(arrays[1][0], threads), np.zeros(3 * h.shape[0]))

    def add(self, x: np.ndarray, y: np.ndarray) -> None:
        """``y += G^T (G x)`` in place (one thread: no numba thread pool at all)."""
        if self.h_cuts.size == 2:
            _vertex_rows(0, self.h_cuts[-1], *self.h, x, self.work, False)
            _vertex_rows(0, self.ht_cuts[-1], *self.ht, self.work, y, True)
        else:
            _vertex_penalty(*self.h, *self.ht, self.h_cuts, self.ht_cuts, x, self.work, y)


def _vertex_factor(g: sp.csr_matrix) -> sp.csr_matrix | None:
    """H (CSR, sorted) when ``g = H (x) I_3`` exactly, else None."""
    g = sp.csr_matrix(g)
    if g.shape[0] % 3 or g.shape[1] % 3:
        return None
    h = sp.csr_matrix(g[::3, ::3])
    h.sort_indices()
    if g.nnz != 3 * h.nnz or (sp.kron(h, sp.identity(3), format="csr") != g).nnz:
        return None
    return h


@numba.njit(cache=True, parallel=True)
def _vertex_penalty(h_ptr: np.ndarray, h_idx: np.ndarray, h_val: np.ndarray, t_ptr: np.ndarray,
                    t_idx: np.ndarray, t_val: np.ndarray, h_cuts: np.ndarray,
                    t_cuts: np.ndarray, x: np.ndarray, work: np.ndarray,
                    y: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``work = (H (x) I_3) x``, then ``y += (H^T (x) I_3) work``, each by row ranges."""
    for t in numba.prange(h_cuts.size - 1):
        _vertex_rows(h_cuts[t], h_cuts[t + 1], h_ptr, h_idx, h_val, x, work, False)
    for t in numba.prange(t_cuts.size - 1):
        _vertex_rows(t_cuts[t], t_cuts[t + 1], t_ptr, t_idx, t_val, work, y, True)


@numba.njit(cache=True)
def _vertex_rows(lo: int, hi: int, indptr: np.ndarray, indices: np.ndarray, data: np.ndarray,
                 x: np.ndarray, y: np.ndarray, add: bool) -> None:  # pragma: no cover (compiled)
    """Rows ``lo .. hi`` of ``y = (M (x) I_3) x`` (``add``: ``y +=``), M in CSR."""
    for c in range(lo, hi):
        a0 = a1 = a2 = 0.0
        for k in range(indptr[c], indptr[c + 1]):
            v, w = 3 * indices[k], data[k]
            a0 += w * x[v]
            a1 += w * x[v + 1]
            a2 += w * x[v + 2]
        if add:
            y[3 * c] += a0
            y[3 * c + 1] += a1
            y[3 * c + 2] += a2
        else:
            y[3 * c], y[3 * c + 1], y[3 * c + 2] = a0, a1, a2


class JacobiPC:
    """``PCPython`` context ``y = D^{-1} x`` with D refreshed in place (``refresh``).

    Used with ``eigen_estimate = "solve"``: the level operator keeps its PETSc object state,
    so the Chebyshev smoother keeps its eigenvalue bounds, while the diagonal follows the
    current Newton matrix.
    """

    def __init__(self, op: Any) -> None:
        self.op = op
        self.inverse = op.createVecs()[0]
        self.refresh()

    def refresh(self) -> None:
        """``D^{-1}`` of the operator's current diagonal."""
        self.op.getDiagonal(self.inverse)
        self.inverse.reciprocal()

    def apply(self, pc: Any, x: Any, y: Any) -> None:  # noqa: ARG002 (petsc4py signature)
        """``y = D^{-1} x``."""
        y.pointwiseMult(x, self.inverse)


@numba.njit(cache=True)
def _upper_blocks(indptr: np.ndarray, indices: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Find the upper 3 x 3 block triangle (block column >= block row) of a CSR pattern.

    One pass per block row: the block columns its three scalar rows reach (sorted), then
    every entry's slot in the row-major 3 x 3 block values.

    Returns:
        ``(positions, slots, bptr, bidx)``: the CSR value positions of the entries, their
        slots in the BSR values (``9 block + 3 (row % 3) + col % 3``), and the BSR row
        pointers and block columns.

    """
    nb = (indptr.size - 1) // 3
    count = 0
    for r in range(indptr.size - 1):
        for k in range(indptr[r], indptr[r + 1]):
            count += indices[k] // 3 >= r // 3
    positions = np.empty(count, dtype=np.int64)
    slots = np.empty(count, dtype=np.int64)
    bptr = np.zeros(nb + 1, dtype=np.int64)
    bidx = np.empty(count, dtype=np.int64)
    mark = np.full(nb, -1, dtype=np.int64)
    slot_of = np.empty(nb, dtype=np.int64)
    i = 0
    for ib in range(nb):
        start = bptr[ib]
        cnt = 0
        for r in range(3 * ib, 3 * ib + 3):
            for k in range(indptr[r], indptr[r + 1]):
                jb = indices[k] // 3
                if jb >= ib and mark[jb] != ib:
                    mark[jb] = ib
                    bidx[start + cnt] = jb
                    cnt += 1
        bidx[start:start + cnt] = np.sort(bidx[start:start + cnt])
        for t in range(cnt):
            slot_of[bidx[start + t]] = start + t
        bptr[ib + 1] = start + cnt
        for r in range(3 * ib, 3 * ib + 3):
            for k in range(indptr[r], indptr[r + 1]):
                c = indices[k]
                if c // 3 >= ib:
                    positions[i] = k
                    slots[i] = 9 * slot_of[c // 3] + 3 * (r % 3) + c % 3
                    i += 1
    return positions, slots, bptr, bidx[:bptr[nb]].copy()


class _SymmetricCopy:
    """A symmetric 3 x 3 block copy (upper block triangle) of an AIJ level matrix.

    The positions of the upper block triangle's entries in the AIJ values are found once
    (the Galerkin patterns are fixed); :meth:`refresh` gathers the current values. The
    product (:meth:`mult`) is a numba pass over the upper blocks adding each block and its
    transpose (:func:`_symmetric_rows`), about 40 % of the AIJ bytes. With ``threads > 1``
    the block rows are split into equal-work ranges, each thread adding into its own vector
    (the transposed blocks reach any row), summed and re-zeroed afterwards by row ranges
    (:func:`_symmetric_parallel`). Timings: docs/notes/multigrid.md.

    Args:
        source: The AIJ matrix.
        values: The source's value array itself when the caller owns it (the fine
            :class:`FineMatrix`): read in place instead of through ``MatGetValuesCSR``, which
            allocates a fresh copy of the whole CSR (225 MB at 160k) at every refresh.
        threads: Threads of the product (>= 1).

    """

    def __init__(self, source: Any, values: np.ndarray | None = None, threads: int = 1) -> None:
        indptr, indices, source_values = source.getValuesCSR()
        self.positions, self.slots, self.bptr, self.bidx = _upper_blocks(indptr, indices)
        # the diagonal is the first upper block of its row (getDiagonal, the kernel); the
        # second test only runs when no block row is empty (its index is then in range)
        if np.any(np.diff(self.bptr) == 0) or np.any(
                self.bidx[self.bptr[:-1]] != np.arange(self.bptr.size - 1)):
            raise InputError("MultigridLinearSystem: a level matrix lacks a diagonal block")
        self.values = np.zeros(9 * self.bidx.size)
        self.source, self.source_values = source, values
        self.values[self.slots] = source_values[self.positions]
        self.diagonal = (9 * self.bptr[:-1, None] + np.array([0, 4, 8])).ravel()
        self.cuts = balanced_cuts(self.bptr, threads)
        self.buffers = np.zeros((threads if threads > 1 else 0, 3 * (self.bptr.size - 1)))
        self.sum_cuts = balanced_cuts(np.arange(3 * self.bptr.size - 2), threads)

    def refresh(self) -> None:
        """Copy the source's current values (same pattern)."""
        values = self.source_values if self.source_values is not None \
            else self.source.getValuesCSR()[2]
        self.values[self.slots] = values[self.positions]

    def mult(self, x: Any, y: Any) -> None:
        """``y = A x`` (PETSc vectors, ``Mat.mult`` signature)."""
        xa, ya = x.getArray(readonly=True), y.getArray()
        if not self.buffers.size:
            ya[:] = 0.0
            _symmetric_rows(0, self.bptr.size - 1, self.bptr, self.bidx, self.values, xa, ya)
        else:
            _symmetric_parallel(self.cuts, self.sum_cuts, self.bptr, self.bidx, self.values, xa,
                                self.buffers, ya)

    def getDiagonal(self, d: Any) -> None:  # noqa: N802 (petsc4py name)
        """``d = diag(A)``."""
        d.getArray()[:] = self.values[self.diagonal]


@numba.njit(cache=True, parallel=True)
def _symmetric_parallel(cuts: np.ndarray, sum_cuts: np.ndarray, bptr: np.ndarray,
                        bidx: np.ndarray, values: np.ndarray, x: np.ndarray,
                        buffers: np.ndarray, y: np.ndarray) -> None:  # pragma: no cover
    """``y = A x``: block-row range t adds into ``buffers[t]``, then the rows are summed."""
    for t in numba.prange(cuts.size - 1):
        _symmetric_rows(cuts[t], cuts[t + 1], bptr, bidx, values, x, buffers[t])
    for t in numba.prange(sum_cuts.size - 1):
        _sum_rows(sum_cuts[t], sum_cuts[t + 1], buffers, y)


@numba.njit(cache=True)
def _symmetric_rows(lo: int, hi: int, bptr: np.ndarray, bidx: np.ndarray, values: np.ndarray,
                    x: np.ndarray, y: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``y += (U_r + U_r^T - D_r) x`` for the upper blocks U_r of block rows ``lo .. hi``.

    ``y`` must be zeroed by the caller; ``values`` holds 9 row-major entries per block.
    """
    for i in range(lo, hi):
        x0, x1, x2 = x[3 * i], x[3 * i + 1], x[3 * i + 2]
        a0 = a1 = a2 = 0.0
        for k in range(bptr[i], bptr[i + 1]):
            j, o = bidx[k], 9 * k
            u0, u1, u2 = x[3 * j], x[3 * j + 1], x[3 * j + 2]
            a0 += values[o] * u0 + values[o + 1] * u1 + values[o + 2] * u2
            a1 += values[o + 3] * u0 + values[o + 4] * u1 + values[o + 5] * u2
            a2 += values[o + 6] * u0 + values[o + 7] * u1 + values[o + 8] * u2
            if j != i:
                y[3 * j] += values[o] * x0 + values[o + 3] * x1 + values[o + 6] * x2
                y[3 * j + 1] += values[o + 1] * x0 + values[o + 4] * x1 + values[o + 7] * x2
                y[3 * j + 2] += values[o + 2] * x0 + values[o + 5] * x1 + values[o + 8] * x2
        y[3 * i] += a0
        y[3 * i + 1] += a1
        y[3 * i + 2] += a2


@numba.njit(cache=True)
def _sum_rows(lo: int, hi: int, buffers: np.ndarray, y: np.ndarray) -> None:  # pragma: no cover
    """``y[lo:hi] = sum_t buffers[t, lo:hi]``, then zero those buffer entries."""
    for i in range(lo, hi):
        total = 0.0
        for t in range(buffers.shape[0]):
            total += buffers[t, i]
            buffers[t, i] = 0.0
        y[i] = total


def _python_operator(product: LowRankOperator) -> Any:
    """Wrap ``A + G^T G`` (or ``A`` alone when g is None) as a matrix-free ``MatPython``."""
    n = product.a.getSize()[0]
    mat: Any = PETSc.Mat().createPython((n, n), product, comm=PETSc.COMM_SELF)
    mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    mat.setUp()
    return mat


class FineMatrix:
    """The fine Newton matrix ``A + tau I`` as a PETSc AIJ wrapping a fixed CSR pattern.

    Args:
        pattern: The Hessian's CSR pattern (all later matrices share it, diagonal included).

    """

    def __init__(self, pattern: sp.csr_matrix) -> None:
        self.indptr = pattern.indptr.astype(PETSc.IntType)
        self.indices = pattern.indices.astype(PETSc.IntType)
        self.values = np.zeros(pattern.nnz, dtype=PETSc.ScalarType)
        rows = np.repeat(np.arange(pattern.shape[0]), np.diff(pattern.indptr))
        self.diagonal = np.flatnonzero(rows == pattern.indices)
        if self.diagonal.size != pattern.shape[0]:
            raise InputError("MultigridLinearSystem: the Hessian pattern must contain the "
                             "diagonal")
        mat: Any = PETSc.Mat()
        mat.createAIJWithArrays(pattern.shape, (self.indptr, self.indices, self.values),
                                bsize=3, comm=PETSc.COMM_SELF)
        mat.assemble()
        self.mat = mat

    def csr(self) -> sp.csr_matrix:
        """Return the current values as a scipy CSR view of the arrays PETSc reads."""
        n = self.indptr.size - 1
        return sp.csr_matrix((self.values, self.indices, self.indptr), shape=(n, n), copy=False)

    def update(self, data: np.ndarray, tau: float) -> None:
        """Copy new values (``+ tau`` on the diagonal); the pattern is unchanged."""
        np.copyto(self.values, data)
        if tau:
            self.values[self.diagonal] += tau
        self.mat.stateIncrease()


@dataclass
class KrylovStats:
    """Counts and wall times of a :class:`MultigridLinearSystem` (seconds).

    Attributes:
        setups: Preconditioner set-ups (Galerkin products + smoother + coarse factorisation).
        eigen_estimates: Set-ups after which the Chebyshev smoothers re-estimate their
            eigenvalue bounds.
        setup_time: Seconds in set-ups.
        solves: CG solves.
        solve_time: Seconds in CG solves (true-residual check and fallbacks included).
        iterations: CG iterations of every solve.
        true_residuals: True relative residual of every accepted CG solution.
        fallbacks: Solves handed to the direct solver.
        fallback_time: Seconds of that in the direct factorisation and solve.
        indefinite_skips: Set-ups whose phase-space matrix was indefinite (their CG ran
            without the phase correction).

    """

    setups: int = 0
    eigen_estimates: int = 0
    setup_time: float = 0.0
    solves: int = 0
    solve_time: float = 0.0
    iterations: list[int] = field(default_factory=list)
    true_residuals: list[float] = field(default_factory=list)
    fallbacks: int = 0
    fallback_time: float = 0.0
    indefinite_skips: int = 0


class NewtonSystem(Protocol):
    """A Newton-system solver (``solvers.shell_newton._LinearSystem`` or multigrid)."""

    def factorize(self, ev: Any, tau: float) -> FactorReport:
        """Factorise ``A + tau I`` of an evaluation."""

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve with the last factorisation."""

    def times(self) -> tuple[float, float, float]:
        """Accumulated (factorise, analysis, solve) seconds."""


class KrylovSystem(NewtonSystem, Protocol):
    """A Newton-system solver by CG to a forcing term (serial or distributed multigrid).

    Attributes:
        stats: Counts and times of its set-ups and solves.
        phase: The wrinkle-phase coarse space, or None.

    """

    stats: KrylovStats
    phase: Any

    def reset_forcing(self) -> None:
        """Start a new Newton solve (no forcing history)."""

    def set_gradient_norm(self, grad_norm: float, target: float = 0.0) -> None:
        """Choose this Newton iteration's CG tolerance from ``||g_k||``."""

    def set_state(self, x: np.ndarray, target: np.ndarray | None) -> None:
        """Positions and penalty target of the next set-up."""


class KrylovBase:
    """State and steps shared by the serial and the distributed multigrid Newton systems.

    The forcing term (:func:`forcing_term`), the once-per-solve Chebyshev bounds, the phase
    space's test-field state and the set-up counts; a subclass sets ``self.phase`` and
    ``self._operators`` (the level operators whose state it increases for new bounds), and
    its CG sets ``self.negative_curvature`` (the last CG met ``p^T A p <= 0``).

    Args:
        options: Krylov / multigrid options.

    """

    def __init__(self, options: MultigridOptions) -> None:
        self.options = options
        self.stats = KrylovStats()
        self.eta = options.rtol
        self.phase: Any = None
        self._grad_history: tuple[float, float] = (0.0, options.ew_max)
        self._operators: list[Any] = []
        self._estimate_due = True
        self._bounds_stale = False
        self.negative_curvature = False
        self._state: tuple[np.ndarray, np.ndarray] | None = None
        self._fields_stale = True
        self.phase_active = True

    def use_phase_space(self, active: bool) -> None:
        """Set whether the phase space (when there is one) serves the coming set-ups at once.

        True (the default): every set-up adds it. False: it stays out (no test fields, no
        ``A_Z``; CG on the multigrid alone) until a CG meets negative curvature of the Newton
        matrix, the sign of a buckling shell, and joins from the next set-up on (:meth:`solve`).
        The caller sets it per Newton solve (:func:`solvers.solver_choice.wrinkled_start`).
        """
        if active and not self.phase_active:
            self._fields_stale = True  # the fields are built anew from the current state
        self.phase_active = bool(active)

    def reset_forcing(self) -> None:
        """Start a new Newton solve: the next forcing term is ``ew_max`` (no history).

        The next set-up also re-estimates the Chebyshev bounds (``eigen_estimate``).
        """
        self._grad_history = (0.0, self.options.ew_max)
        self._estimate_due = True

    def set_gradient_norm(self, grad_norm: float, target: float = 0.0) -> None:
        """Choose the CG tolerance of this Newton iteration from ``||g_k||`` (forcing term).

        Called once per Newton iteration: from now on the Chebyshev bounds of earlier
        iterations count as stale (see :meth:`solve`). ``target`` is the Newton gradient
        tolerance (0 = unknown): with ``target_fraction`` the CG tolerance is raised to
        ``min(ew_max, target_fraction target / ||g_k||)`` when that is larger, since the
        linearised gradient after the step, ``||g_k + A dx|| <= eta ||g_k||``, then already
        lies below ``target_fraction`` times the tolerance.
        """
        self._bounds_stale = True
        self.eta, self._grad_history = forcing_term(self.options, grad_norm,
                                                    self._grad_history, target)

    def set_state(self, x: np.ndarray, target: np.ndarray | None) -> None:
        """Positions and penalty target of the next set-up (the phase space's test fields)."""
        if self.phase is None:
            return
        state = field_state(self.phase.rest, x, target)
        if not same_state(state, self._state):
            self._state, self._fields_stale = state, True

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """CG to the forcing term; :meth:`_failed` when CG does not pass.

        With ``eigen_estimate = "solve"`` a failed CG whose Chebyshev bounds come from an
        earlier Newton iteration gets new bounds (an underestimated ``lambda_max`` makes the
        smoother amplify, the preconditioner indefinite) and is repeated once with them,
        unless it met negative curvature of the matrix itself (``negative_curvature``, set
        by the subclass's CG: ``p^T A p <= 0``, which no preconditioner changes); then the
        shell Newton's next shift uses the new bounds, and an inactive phase space joins
        (:meth:`use_phase_space`). Bounds estimated in this Newton
        iteration stay valid for its shifted retries, since a shift ``tau`` only moves the
        spectrum of ``(D + tau)^{-1} (A + tau I)`` towards 1.
        """
        start = time.perf_counter()
        try:
            x = self._accepted_cg(rhs)
            if x is None and self._bounds_stale and self.options.eigen_estimate == "solve":
                self.renew_bounds()
                if not self.negative_curvature:
                    x = self._accepted_cg(rhs)
            if x is None and self.negative_curvature and self.phase is not None:
                self.use_phase_space(True)  # buckling: the space joins (use_phase_space)
            return x if x is not None else self._failed(rhs)
        finally:
            self.stats.solves += 1
            self.stats.solve_time += time.perf_counter() - start

    def _accepted_cg(self, rhs: np.ndarray) -> np.ndarray | None:
        """One CG solve; its solution if it passed the true-residual test (subclass)."""
        raise NotImplementedError

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Return the current system's matrix times ``x`` (a serial subclass's product)."""
        raise NotImplementedError

    def true_residual(self, x: np.ndarray, rhs: np.ndarray) -> float:
        """``||b - A x|| / ||b||`` of the current system (:meth:`apply`)."""
        norm_b = float(np.linalg.norm(rhs)) or 1.0
        return float(np.linalg.norm(rhs - self.apply(x))) / norm_b

    def _kept(self, x: np.ndarray, rhs: np.ndarray, converged: bool) -> np.ndarray | None:
        """Return ``x`` if CG converged to a true residual within the slack, else None.

        The slack is ``residual_slack`` times the forcing term; a kept residual is recorded.
        """
        residual = self.true_residual(x, rhs) if converged else np.inf
        if residual > self.options.residual_slack * self.eta:
            return None
        self.stats.true_residuals.append(residual)
        return x

    def _failed(self, rhs: np.ndarray) -> np.ndarray:
        """Return the direction when CG failed (subclass: a fallback solve, or NaN)."""
        raise NotImplementedError

    def renew_bounds(self) -> None:
        """Make the finest level's Chebyshev smoother re-estimate its bounds at the next solve.

        The coarser levels' operators change state too, but PCMG sets their smoothers up
        again only when their operators are set again: they keep the bounds of the KSP's
        first set-up. Setting them again (all levels re-estimated) was measured not to pay
        (docs/notes/multigrid.md, "Chebyshev bounds of the coarser levels").
        """
        for op in self._operators:
            op.stateIncrease()
        self.stats.eigen_estimates += 1
        self._bounds_stale = False

    def _setup_done(self, start: float, report: FactorReport) -> FactorReport:
        """Count a set-up begun at ``start``; the report with its time."""
        elapsed = time.perf_counter() - start
        self.stats.setups += 1
        self.stats.setup_time += elapsed
        return replace(report, numeric_time=elapsed)


class MultigridLinearSystem(KrylovBase):
    """CG + geometric multigrid (PETSc PCMG) for ``(A + tau I + G^T G) dx = b``.

    Same interface as the direct Newton-system solver (``factorize(ev, tau)``, ``solve(b)``,
    ``times()``): ``factorize`` sets the preconditioner up (no factorisation of the fine
    matrix), ``solve`` runs CG to the current forcing term and checks the true residual.

    Args:
        prolongations: ``P_l`` coarse to fine, ``P_l`` of shape ``(3 n_{l+1}, 3 n_l)``, the
            last one ending at the shell's dofs (:meth:`ShellHierarchy.prolongations`).
        options: Krylov / multigrid options.
        fallback: Direct solver used when CG fails (None: no fallback).
        geometry: Rest vertices and faces of the shell (``options.phase_space`` needs them).

    """

    def __init__(self, prolongations: tuple[sp.csr_matrix, ...], options: MultigridOptions,
                 fallback: NewtonSystem | None = None,
                 geometry: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        if not prolongations:
            raise InputError("MultigridLinearSystem: the hierarchy needs >= 1 subdivision "
                             "level")
        for fine, coarse in zip(prolongations[1:], prolongations[:-1], strict=True):
            if fine.shape[1] != coarse.shape[0]:
                raise InputError("MultigridLinearSystem: prolongation shapes do not chain")
        super().__init__(options)
        self.p_scipy = tuple(sp.csr_matrix(p) for p in prolongations)
        self.p_mats = [petsc_aij(p, block=3) for p in self.p_scipy]
        self.fallback = fallback
        self.n = self.p_scipy[-1].shape[0]
        self._fine: FineMatrix | None = None
        self._galerkin: list[Any] = []
        self._chain: GalerkinChain | None = None
        self._levels_shift = 0.0
        self._g_source: sp.csr_matrix | None = None
        self._g_levels: list[sp.csr_matrix | None] = []
        self._coarse_penalty: sp.csr_matrix | None = None
        self._coarse: Any = None
        self._coarse_pattern: sp.csr_matrix | None = None
        self._ksp: Any = None
        self._current: tuple[Any, float] | None = None
        self._jacobi: list[JacobiPC] = []
        self._products: list[LowRankOperator] = []
        self._sbaij: list[_SymmetricCopy] = []
        self.phase = self._phase_space(geometry)
        self._deflated: Any = None
        self._phase_ready = False
        self._pc_vecs: tuple[Any, Any] | None = None

    def _phase_space(self, geometry: tuple[np.ndarray, np.ndarray] | None) -> PhaseSpace | None:
        """Build the :class:`~solvers.phase_space.PhaseSpace` when ``options.phase_space``."""
        if not self.options.phase_space:
            return None
        if geometry is None:
            raise InputError("MultigridOptions.phase_space: needs the shell's rest geometry "
                             "(MultigridLinearSystem(..., geometry=(vertices, faces)))")
        vertex_matrices = tuple(p[::3, ::3].tocsr() for p in self.p_scipy)
        return PhaseSpace(*geometry, hat_matrix(vertex_matrices, self.options.phase_level),
                          self.options.threads)

    # ----------------------------------------------------------------------------- set-up

    def factorize(self, ev: Any, tau: float) -> FactorReport:
        """Set the preconditioner up for ``ev.hess + tau I (+ G^T G)``.

        Always "succeeds": whether the matrix is positive definite enough is CG's to find
        (negative curvature fails the solve, the shell Newton then moves on to the next
        shift). With the phase space, a Galerkin matrix ``Z^T A Z`` with negative pivots
        (A indefinite on ``span Z``) leaves the correction out of that matrix's CG; stopping
        the set-up there instead pinned the shift on a saddle of the bent bar for 300
        iterations (docs/notes/phase-space.md).
        """
        start = time.perf_counter()
        if ev.hess is None:
            raise InputError("energy.evaluate(order=2) returned no Hessian")
        hess = sp.csr_matrix(ev.hess)
        if hess.shape != (self.n, self.n):
            raise InputError(f"MultigridLinearSystem: Hessian of shape {hess.shape}, the "
                             f"hierarchy ends at {self.n} dofs")
        if self._fine is None:
            self._fine = FineMatrix(hess)
        self._fine.update(hess.data, tau)
        self._set_penalty(ev.penalty_factor)
        same_matrix = self._current is not None and self._current[0] is ev
        self._current = (ev, tau)
        phase = self._update_phase(hess, ev.penalty_factor, tau, same_matrix)
        if phase is not None and phase.indefinite:
            self.stats.indefinite_skips += 1
        self._galerkin_products(tau, new_matrix=not same_matrix)
        self._finish_setup()
        return self._setup_done(start, FactorReport(success=True, shift=float(tau)))

    def _finish_setup(self) -> None:
        """Coarse matrix, level operators, smoothers and the KSPs on the current levels."""
        self._update_coarse()
        if self._ksp is None:
            self._ksp = self._create_ksp()
        self._refresh_products()
        self._refresh_smoothers()
        self._ksp.setUp()
        if self.phase is not None and self._deflated is None:
            self._deflated = self._deflated_ksp()

    def _update_phase(self, hess: sp.csr_matrix, g: sp.csr_matrix | None, tau: float,
                      same_matrix: bool) -> FactorReport | None:
        """Phase space: new test fields, Galerkin matrix and its factorisation (None: off).

        ``hess``: the Newton matrix without the shift ``tau``. ``same_matrix``: the
        evaluation of the last set-up with another shift; with the same state
        (:meth:`set_state`) the Galerkin matrix is shifted instead of recomputed.
        ``_phase_ready`` says whether CG uses the correction (its matrix factorised and SPD).
        """
        self._phase_ready = False
        if self.phase is None or not self.phase_active:
            return None
        report = self.phase.refresh(hess, g, tau, self._state,
                                    same_matrix and not self._fields_stale)
        self._fields_stale = False
        self._phase_ready = report.usable_spd
        return report

    def _deflated_ksp(self) -> Any:
        """CG from ``x_0 = Q b`` preconditioned by A-DEF2 around PCMG (phase space only)."""
        assert self.phase is not None  # only with the phase space (internal invariant)
        return deflated_cg(PETSc.COMM_SELF, self._operators[-1], self._ksp.getPC(), self.phase)

    def _set_penalty(self, g: sp.csr_matrix | None) -> None:
        """Build the constant chain ``G_l = G_{l+1} P_l`` (again only if G changes)."""
        if g is self._g_source and self._g_levels:
            return
        self._g_source = g
        self._g_levels = penalty_levels(g, self.p_scipy)
        g0 = self._g_levels[0]
        self._coarse_penalty = None if g0 is None else (g0.T @ g0).tocsr()
        self._coarse_pattern = None
        self._ksp = None  # the level operators change: rebuilt by _update_coarse/_create_ksp
        self._deflated = None

    def _galerkin_products(self, tau: float, new_matrix: bool) -> None:
        """``A_l = P_l^T A_{l+1} P_l`` from the finest down, over 3 x 3 vertex blocks.

        Or, for the last set-up's matrix with another shift, its levels with the shift moved
        to ``tau`` (:func:`shift_images`; exact, no new products).
        """
        assert self._fine is not None  # set by factorize (internal invariant)
        if self._chain is None:
            vertex = tuple(p[::3, ::3] for p in self.p_scipy)
            self._chain = GalerkinChain(self._fine.csr(), vertex, self.options.threads)
            self._chain.set_shift_images(shift_images(vertex)[::-1])
        if not new_matrix and self._galerkin:
            mats = self._chain.shift(tau - self._levels_shift)
        else:
            mats = self._chain.update(self._fine.values)
        self._levels_shift = tau
        self._galerkin = [*mats, self._fine.mat]

    def _update_coarse(self) -> None:
        """Assemble ``A_0 + G_0^T G_0`` (the constant penalty part kept) into the coarse matrix."""
        assert self._chain is not None  # set with the Galerkin levels (internal invariant)
        a0 = self._chain.products[-1].csr
        penalty = self._coarse_penalty
        total = a0 if penalty is None else (a0 + penalty).tocsr()
        total.sort_indices()
        if self._coarse is None or self._coarse_pattern is None \
                or total.nnz != self._coarse_pattern.nnz:
            self._coarse_pattern = total
            self._coarse = petsc_aij(total)
            self._ksp = None
            self._deflated = None
            return
        self._coarse.setValuesCSR(total.indptr.astype(PETSc.IntType),
                                  total.indices.astype(PETSc.IntType), total.data)
        self._coarse.assemble()

    def _refresh_smoothers(self) -> None:
        """Make the smoothers see the new level operators.

        An object-state increase makes every Chebyshev smoother re-estimate its eigenvalue
        bounds at the next solve (counted in ``KrylovStats.eigen_estimates``); with
        ``eigen_estimate = "solve"`` that happens once per Newton solve and the other set-ups
        only refresh the Jacobi diagonals.
        """
        for jacobi in self._jacobi:
            jacobi.refresh()
        if self._estimate_due:
            self.renew_bounds()
            self._estimate_due = self.options.eigen_estimate == "setup"

    def _refresh_products(self) -> None:
        """Point the level operators at this set-up's ``A_l`` (an SBAIJ copy if asked)."""
        if self.options.level_format == "aij":
            return
        if len(self._sbaij) != len(self._products):
            # the next coarser product and the coarse solve read the AIJ values: copy
            assert self._fine is not None  # set by factorize (internal invariant)
            assert self._chain is not None  # set with the Galerkin levels (internal invariant)
            threads = self.options.threads
            self._sbaij = [*(_SymmetricCopy(b.mat, b.values, threads)
                             for b in reversed(self._chain.products[:-1])),
                           _SymmetricCopy(self._fine.mat, self._fine.values, threads)]
        for product, copy in zip(self._products, self._sbaij, strict=True):
            copy.refresh()
            product.a = copy

    def _level_operators(self) -> list[Any]:
        """Per level (coarse to fine): the assembled coarse matrix, then ``A_l + G_l^T G_l``.

        Every fine level is a ``MatPython`` (penalty or not) whose object state only changes
        when new eigenvalue bounds are due (``eigen_estimate``) and whose product matrix is
        swapped for the SBAIJ copy (``level_format``).
        """
        self._products = [LowRankOperator(a, g, self.options.threads)
                          for a, g in zip(self._galerkin[1:], self._g_levels[1:], strict=True)]
        return [self._coarse, *(_python_operator(p) for p in self._products)]

    def _smoother_matrix(self, level: int, op: Any) -> Any:
        """Matrix the level smoother's PC reads: ``op``, or the AIJ ``A_l`` for SOR."""
        if self.options.smoother_pc == "sor" and level > 0:
            return self._galerkin[level]
        return op

    def _create_ksp(self) -> Any:
        """CG (unpreconditioned norm) + PCMG: Chebyshev/Jacobi levels, MUMPS coarse."""
        self._operators = self._level_operators()
        smoothers = [self._smoother_matrix(level, op) for level, op in enumerate(self._operators)]
        ksp, self._jacobi = multigrid_cg(PETSc.COMM_SELF, self._operators, smoothers,
                                         self.p_mats, self.options, f"wrinkles_mg{id(self)}_")
        self._estimate_due = self._estimate_due or bool(self._jacobi)
        return ksp

    # ----------------------------------------------------------------------------- solve

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """Return one V-cycle (the PCMG preconditioner, from zero) applied to ``r``.

        The cycle is symmetric (Chebyshev smoothing before and after, the coarsest level
        solved exactly), so it can precondition an outer CG (:mod:`solvers.joint_krylov`).
        """
        assert self._ksp is not None  # factorize() set it up (internal invariant)
        if self._pc_vecs is None:  # the fine size never changes: one pair for every call
            self._pc_vecs = self._operators[-1].createVecs()
        b, x = self._pc_vecs
        b.setArray(np.ascontiguousarray(r, dtype=np.float64))
        self._ksp.getPC().apply(b, x)
        return x.getArray().copy()

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Return ``(A + tau I + G^T G) x`` of the current system (scipy; true residuals)."""
        assert self._current is not None  # factorize() ran first (internal invariant)
        return shifted_product(*self._current, x)

    def _accepted_cg(self, rhs: np.ndarray) -> np.ndarray | None:
        """CG from zero; the solution if it converged to a true residual within the slack."""
        x, its, reason = self._cg(rhs)
        self.stats.iterations.append(its)
        self.negative_curvature = reason == PETSc.KSP.ConvergedReason.DIVERGED_INDEFINITE_MAT
        return self._kept(x, rhs, reason > 0)

    def _cg(self, rhs: np.ndarray) -> tuple[np.ndarray, int, int]:
        """``(x, iterations, converged reason)`` of one CG solve from x = 0."""
        ksp = self._deflated if self._phase_ready else self._ksp
        b, x = self._operators[-1].createVecs()
        b.setArray(np.ascontiguousarray(rhs, dtype=np.float64))
        x.set(0.0)
        if self._phase_ready:
            ksp.getPC().getPythonContext().start(b, x)
        ksp.setTolerances(rtol=self.eta, atol=0.0, max_it=self.options.max_iterations)
        ksp.solve(b, x)
        out = x.getArray().copy()
        for vec in (b, x):
            vec.destroy()
        return out, int(ksp.getIterationNumber()), int(ksp.getConvergedReason())

    def _failed(self, rhs: np.ndarray) -> np.ndarray:
        """Solve the current system directly, or NaN (a failed direction) without fallback."""
        if self.fallback is None or not self.options.fallback or self._current is None:
            return np.full(self.n, np.nan)
        start = time.perf_counter()
        ev, tau = self._current
        report = self.fallback.factorize(ev, tau)
        self.stats.fallbacks += 1
        out = self.fallback.solve(rhs) if report.usable_spd else np.full(self.n, np.nan)
        self.stats.fallback_time += time.perf_counter() - start
        return out

    def times(self) -> tuple[float, float, float]:
        """Return (set-up, analysis, CG solve) seconds, the direct fallback's included."""
        direct = self.fallback.times() if self.fallback is not None else (0.0, 0.0, 0.0)
        return (self.stats.setup_time + direct[0], direct[1],
                self.stats.solve_time - self.stats.fallback_time + direct[2])


def gram_diagonal(g: sp.spmatrix) -> np.ndarray:
    """``diag(G^T G)``: the column sums of ``G .* G`` (the penalty's share of the diagonal)."""
    return np.asarray(sp.csr_matrix(g).multiply(g).sum(axis=0)).ravel()


def shifted_product(ev: Any, tau: float, x: np.ndarray) -> np.ndarray:
    """Return ``(A + tau I + G^T G) x`` with ``A = ev.hess`` and ``G = ev.penalty_factor``."""
    out = ev.hess @ x + tau * x
    if ev.penalty_factor is not None:
        out += ev.penalty_factor.T @ (ev.penalty_factor @ x)
    return np.asarray(out)


def shift_images(prolongations: tuple[sp.csr_matrix, ...] | list[sp.csr_matrix]
                 ) -> list[sp.csr_matrix]:
    r"""Galerkin images ``M_l = Q_l^T Q_l`` of the identity on every level below the finest.

    ``Q_l = P_{L-1} \cdots P_l`` prolongs level l to the finest (coarse to fine, ``M_l =
    P_l^T M_{l+1} P_l`` with ``M_L = I``). The Galerkin product is linear, so the levels of
    ``A + tau' I`` are those of ``A + tau I`` plus ``(tau' - tau) M_l``: a change of shift
    without new products. CSR (scalar or vertex-level, as the prolongations), sorted,
    coarse to fine.
    """
    images: list[sp.csr_matrix] = []
    m = sp.identity(prolongations[-1].shape[0], format="csr")
    for p in reversed(prolongations):
        m = sp.csr_matrix(p.T @ m @ p)
        m.sort_indices()
        images.append(m)
    return images[::-1]


def penalty_levels(g: sp.csr_matrix | None, prolongations: tuple[sp.csr_matrix, ...]
                   ) -> list[sp.csr_matrix | None]:
    """Return the penalty factor on every level, coarse to fine: ``G_l = G_{l+1} P_l``."""
    chain: list[sp.csr_matrix | None] = [None if g is None else sp.csr_matrix(g)]
    for p in reversed(prolongations):
        chain.append(None if chain[-1] is None else (chain[-1] @ p).tocsr())
    return chain[::-1]


def galerkin_levels(fine: Any, prolongations: list[Any], levels: list[Any]) -> list[Any]:
    """``A_l = P_l^T A_{l+1} P_l`` from ``fine`` down, coarse to fine (serial or distributed).

    ``levels`` from an earlier call (same patterns) are refilled in place, the symbolic
    products reused; ``[]`` creates them.
    """
    if not levels:
        mats = [fine]
        for p in reversed(prolongations):
            mats.append(mats[-1].PtAP(p))
        return mats[::-1]
    for level in range(len(prolongations) - 1, -1, -1):
        levels[level + 1].PtAP(prolongations[level], result=levels[level])
    return levels


def multigrid_cg(comm: Any, operators: list[Any], smoothers: list[Any], interpolations: list[Any],
                 options: MultigridOptions, prefix: str) -> tuple[Any, list[JacobiPC]]:
    """CG (unpreconditioned norm) preconditioned by PCMG, set up; serial or distributed.

    Args:
        comm: Communicator of the matrices.
        operators: Level operators, coarse (assembled, MUMPS Cholesky) to fine (the CG's).
        smoothers: The matrix each level's smoother PC reads (the operator, or an assembled
            ``A_l`` for SOR).
        interpolations: ``P_l`` from level l - 1 to level l, coarse to fine.
        options: Cycle, Chebyshev degree, smoother PC, eigenvalue-estimate policy.
        prefix: Options prefix of this solver (the level options are set below it).

    Returns:
        The KSP and, with ``eigen_estimate = "solve"``, the fine levels' Jacobi contexts
        (:class:`JacobiPC`, refreshed by the caller at every set-up), else ``[]``.

    """
    ksp: Any = PETSc.KSP().create(comm)
    ksp.setOptionsPrefix(prefix)
    ksp.setType("cg")
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    pc: Any = ksp.getPC()
    pc.setType("mg")
    pc.setMGLevels(len(operators))
    pc.setMGType(PETSc.PC.MGType.MULTIPLICATIVE)
    pc.setMGCycleType(PETSc.PC.MGCycleType.V if options.cycle == "v"
                      else PETSc.PC.MGCycleType.W)
    for level, p in enumerate(interpolations, start=1):
        pc.setMGInterpolation(level, p)
    for level, (op, smoother) in enumerate(zip(operators, smoothers, strict=True)):
        pc.getMGSmoother(level).setOperators(op, smoother)
    ksp.setOperators(operators[-1])
    python = options.eigen_estimate == "solve"
    coarse_amg = coarse_by_amg(operators[0].getSize()[0], len(operators), comm.size,
                               options.phase_space)
    values = pcmg_options(options.smoother_degree, "python" if python else options.smoother_pc,
                          distributed=comm.size > 1, coarse_amg=coarse_amg)
    db = PETSc.Options()
    for key, value in values.items():
        db.setValue(prefix + key, value)
    try:  # the level smoothers read the options database during the first PCSetUp only
        ksp.setFromOptions()
        jacobi = [JacobiPC(op) for op in operators[1:]] if python else []
        for level, context in enumerate(jacobi, start=1):
            level_pc = pc.getMGSmoother(level).getPC()
            level_pc.setType(PETSc.PC.Type.PYTHON)
            level_pc.setPythonContext(context)
        ksp.setUp()
    finally:
        for key in values:
            db.delValue(prefix + key)
    return ksp, jacobi


COARSE_AMG_FROM: int = 2000
"""Coarse-level unknowns from which the V-cycle's coarse solve is one algebraic multigrid cycle
(PETSc's GAMG) instead of a Cholesky factorisation (:func:`coarse_by_amg`)."""


def coarse_by_amg(unknowns: int, levels: int, ranks: int, deflated: bool) -> bool:
    """Whether a coarse level of ``unknowns`` is one GAMG cycle rather than a Cholesky factor.

    From :data:`COARSE_AMG_FROM` unknowns: in a one-level hierarchy (``levels == 2``: the
    coarse level is the body's whole surface, a quarter to a half of the shell), and in a
    deeper hierarchy over several ranks (``ranks > 1``) whose CG the phase space deflates
    (``deflated``): a Cholesky coarse level is factorised and solved whole on every rank at
    every set-up and V-cycle, the GAMG cycle runs over the ranks' own rows. A deeper serial
    hierarchy keeps the Cholesky (there the two cost the same and the Cholesky is the
    stronger coarse solve), and so does a V-cycle without the phase space (the two-way joint
    CG's shell block, where the weaker coarse solve costs more CG iterations than it saves;
    docs/notes/multigrid.md).
    """
    return unknowns >= COARSE_AMG_FROM and (levels == 2 or (ranks > 1 and deflated))


def pcmg_options(degree: int, smoother_pc: str, distributed: bool = False,
                 coarse_amg: bool = False) -> dict[str, str]:
    """PETSc options (below the solver's prefix) of the level smoothers and the coarse solve.

    ``coarse_amg`` (:func:`coarse_by_amg`: a large coarse level): the coarse level is applied
    as one GAMG V-cycle (PCGAMG's defaults, smoothed aggregation and Chebyshev smoothers: a
    fixed symmetric operator, so the outer CG stays CG), set up again at every Newton matrix;
    a Cholesky of the elbow's 2 523 coarse unknowns cost 87 MFlop and most of the frames' CG
    time (docs/notes/multigrid.md). Any other coarse
    level is factorised by MUMPS Cholesky in METIS's ordering (``ICNTL(7) = 5``, as the
    direct path). Over several ranks a Cholesky coarse level is held whole by every rank and
    solved there alone (``PCREDUNDANT``: a distributed solve of a small system costs its
    messages, not its arithmetic, and every rank count applies the same coarse operator); a
    GAMG coarse level runs over the ranks on their own rows, its aggregates then depending on
    the partition (a redundant cycle would repeat the whole coarse work on every rank;
    measurements in docs/notes/multigrid.md).
    """
    redundant = distributed and not coarse_amg
    coarse = "mg_coarse_redundant_" if redundant else "mg_coarse_"
    solve = ({f"{coarse}pc_type": "gamg"} if coarse_amg else
             {f"{coarse}pc_type": "cholesky", f"{coarse}pc_factor_mat_solver_type": "mumps",
              f"{coarse}mat_mumps_icntl_7": str(MUMPS_ORDERINGS["metis"])})
    return {
        "mg_levels_ksp_type": "chebyshev",
        "mg_levels_ksp_max_it": str(degree),
        "mg_levels_ksp_chebyshev_esteig": "0,0.1,0,1.1",
        "mg_levels_pc_type": smoother_pc,
        "mg_coarse_ksp_type": "preonly",
        **({"mg_coarse_pc_type": "redundant"} if redundant else {}),
        **solve,
    }
