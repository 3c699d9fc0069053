"""Sparse direct solvers for the shell Hessian, with the symbolic analysis done once.

The shell Hessian has a constant sparsity pattern (MISSION.md section 6): the fill-reducing
ordering and the symbolic factorisation are computed on the first factorisation and reused by
every later Newton iteration and frame, which then only pay the numeric factorisation.

Backends (serial, ``PETSc.COMM_SELF``):

* ``mumps``: MUMPS through PETSc's PCFactor. ``cholesky`` flags the matrix SPD (MUMPS
  ``SYM = 1``, LL^T), ``ldlt`` uses the general symmetric LDL^T (``SYM = 2``, with 2x2 pivots),
  ``lu`` the unsymmetric LU (``SYM = 0``). ``INFOG(1) < 0`` is a failed factorisation and
  ``INFOG(12)`` counts the negative pivots of a symmetric factorisation (the number of
  negative eigenvalues, Sylvester's law of inertia).
* ``petsc``: PETSc's native sparse Cholesky / LU; its inertia comes from ``MatGetInertia``.
* ``superlu_dist``: SuperLU_DIST LU (no inertia).
* ``scipy``: ``scipy.sparse.linalg.splu`` (SuperLU). For ``cholesky`` / ``ldlt`` it runs in
  symmetric mode (minimum degree on A^T + A, diagonal pivoting), so ``P A P^T = L U`` with
  ``U = D L^T`` and the inertia is the sign count of ``diag(U)``. It cannot reuse the analysis.

The PETSc matrix is built once. With ``matrix_format = "aij"`` it *wraps* the CSR arrays
(``MatCreateSeqAIJWithArrays``): a refactorisation copies the new values into that array and
increases the object state, so PETSc sees the same nonzero state and PCFactor skips the
symbolic phase. ``"sbaij"`` stores the upper block triangle with 3x3 vertex blocks
(``MATSEQSBAIJ``, bs = 3) for Cholesky / LDL^T and updates it with ``MatSetValuesBlocked``.

The penalty W_P = k_P ||H (x - y)||^2 has the low-rank Hessian G^T G (G = sqrt(2 k_P) H (x) I_3);
:class:`AugmentedPenaltySolver` solves ``(A + G^T G) dx = -g`` as the quasi-definite system
``[[A, G^T], [G, -I]] [dx; mu] = [-g; 0]`` without forming G^T G (its block pattern is
assembled once).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from meshes.errors import InputError
from models.backend import PETSc

BACKENDS: tuple[str, ...] = ("mumps", "superlu_dist", "petsc", "scipy")
FACTORIZATIONS: tuple[str, ...] = ("cholesky", "ldlt", "lu")
MATRIX_FORMATS: tuple[str, ...] = ("aij", "sbaij")
MUMPS_ORDERINGS: dict[str, int] = {"amd": 0, "amf": 2, "scotch": 3, "pord": 4, "metis": 5,
                                   "qamd": 6, "auto": 7}
PETSC_ORDERINGS: tuple[str, ...] = ("nd", "rcm", "qmd", "1wd", "natural", "amd", "metis")
SCIPY_ORDERINGS: tuple[str, ...] = ("COLAMD", "MMD_AT_PLUS_A", "MMD_ATA", "NATURAL")
SUPERLU_DIST_ORDERINGS: tuple[str, ...] = ("MMD_AT_PLUS_A", "MMD_ATA", "NATURAL", "COLAMD")
"""SuperLU_DIST column orderings; the wheel's SuperLU_DIST has no METIS (METIS_AT_PLUS_A aborts)."""
BLOCK_SIZE: int = 3
"""Vertex block size of the shell Hessian (3 dofs per vertex, ``models/shell/dofs.py``)."""

_FACTOR_EVENTS: dict[str, tuple[str, str]] = {
    "cholesky": ("MatCholFctrSym", "MatCholFctrNum"),
    "ldlt": ("MatCholFctrSym", "MatCholFctrNum"),
    "lu": ("MatLUFactorSym", "MatLUFactorNum"),
}


def _require_choice(name: str, value: Any, choices: tuple[Any, ...]) -> None:
    """Raise InputError naming ``name`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise InputError(f"{name}: expected one of {list(choices)}, got {value!r}")


def default_ordering(backend: str) -> str:
    """Return the fill-reducing ordering used when ``LinearSolverOptions.ordering`` is empty."""
    return {"mumps": "metis", "petsc": "nd", "superlu_dist": "MMD_AT_PLUS_A",
            "scipy": "MMD_AT_PLUS_A"}[backend]


def _valid_orderings(backend: str) -> tuple[str, ...]:
    """Orderings accepted by ``backend``."""
    return {"mumps": tuple(MUMPS_ORDERINGS), "petsc": PETSC_ORDERINGS,
            "superlu_dist": SUPERLU_DIST_ORDERINGS, "scipy": SCIPY_ORDERINGS}[backend]


@dataclass(frozen=True)
class LinearSolverOptions:
    """Options of :class:`SparseDirectSolver`.

    Attributes:
        backend: "mumps" | "superlu_dist" | "petsc" | "scipy".
        symmetric: Factorisation of the symmetric matrix: "cholesky" (LL^T, expects SPD),
            "ldlt" (symmetric indefinite LDL^T; mumps only) or "lu". superlu_dist only does "lu".
        matrix_format: PETSc storage, "aij" (full CSR, wrapped without copy) or "sbaij"
            (upper block triangle, bs = 3; mumps cholesky / ldlt only: PETSc's own SBAIJ
            Cholesky cannot reorder).
        ordering: Fill-reducing ordering; "" picks :func:`default_ordering` (METIS for MUMPS,
            ICNTL(7) = 5; nested dissection for petsc; MMD_AT_PLUS_A for superlu_dist, scipy).
        mumps_icntl: Extra MUMPS ``(index, value)`` integer controls, applied last.
        mumps_blr: MUMPS block low-rank factorisation (ICNTL(35) = 1; False = full rank);
            systems below ~3k vertices are factorised exactly whatever it says.
        mumps_blr_tolerance: BLR dropping tolerance CNTL(7) (relative, dimensionless); the
            true residual of a solve is about 0.1 x this value.
        mumps_refinement: Maximum iterative refinement steps per solve (ICNTL(10); 0 = off);
            acts only when the factor is inexact (BLR tolerance above ~1e-8).
        mumps_out_of_core: Write the factors to disk (ICNTL(22) = 1, directory
            ``$MUMPS_OOC_TMPDIR``, default /tmp; removed with the factor).

    Measured choices of these defaults: docs/notes/linear-solver-defaults.md.

    """

    backend: str = "mumps"
    symmetric: str = "cholesky"
    matrix_format: str = "aij"
    ordering: str = ""
    mumps_icntl: tuple[tuple[int, int], ...] = ()
    mumps_blr: bool = True
    mumps_blr_tolerance: float = 1e-10
    mumps_refinement: int = 0
    mumps_out_of_core: bool = False

    def __post_init__(self) -> None:
        _require_choice("LinearSolverOptions.backend", self.backend, BACKENDS)
        _require_choice("LinearSolverOptions.symmetric", self.symmetric, FACTORIZATIONS)
        _require_choice("LinearSolverOptions.matrix_format", self.matrix_format, MATRIX_FORMATS)
        if self.ordering:
            _require_choice("LinearSolverOptions.ordering", self.ordering,
                            _valid_orderings(self.backend))
        self._check_combination()
        if not self.mumps_blr_tolerance > 0:
            raise InputError("LinearSolverOptions.mumps_blr_tolerance: must be > 0, got "
                             f"{self.mumps_blr_tolerance!r}")
        if not 0 <= self.mumps_refinement <= 100:
            raise InputError("LinearSolverOptions.mumps_refinement: expected 0..100 steps, got "
                             f"{self.mumps_refinement!r}")
        for pair in self.mumps_icntl:
            if len(pair) != 2:
                raise InputError(f"LinearSolverOptions.mumps_icntl: entries are (index, value) "
                                 f"pairs, got {pair!r}")

    def _check_combination(self) -> None:
        """Reject backend / factorisation / format combinations no backend implements."""
        if self.backend == "superlu_dist" and self.symmetric != "lu":
            raise InputError("LinearSolverOptions.symmetric: superlu_dist only does 'lu', got "
                             f"{self.symmetric!r}")
        if self.backend == "petsc" and self.symmetric == "ldlt":
            raise InputError("LinearSolverOptions.symmetric: petsc has no pivoting LDL^T; use "
                             "'cholesky' or backend 'mumps'")
        if self.matrix_format == "sbaij" and (self.symmetric == "lu" or self.backend != "mumps"):
            # PETSc's own SBAIJ Cholesky only supports the natural ordering (no fill reduction)
            raise InputError("LinearSolverOptions.matrix_format: 'sbaij' needs backend mumps "
                             f"with cholesky/ldlt, got {self.backend}/{self.symmetric}")

    @property
    def resolved_ordering(self) -> str:
        """The ordering actually used (``ordering`` or the backend default)."""
        return self.ordering or default_ordering(self.backend)


@dataclass(frozen=True)
class ShiftOptions:
    """Diagonal shift ``A + tau I`` used when a factorisation fails or is indefinite.

    ``tau_0 = initial * mean(|diag A|)``, then ``tau_{j+1} = growth * tau_j`` (Nocedal & Wright,
    Numerical Optimization, Alg. 3.3 "Cholesky with added multiple of the identity").

    Attributes:
        initial: First shift relative to the mean absolute diagonal (dimensionless).
        growth: Factor between consecutive shifts (> 1). The textbook 10 is the default; the
            scenes under a static load select 5 (:mod:`solvers.solver_choice`,
            docs/notes/shift-schedule.md).
        max_shifts: Number of shifted attempts before giving up (>= 1): the largest shift is
            ``initial * growth^(max_shifts - 1)`` x the mean diagonal (1e7 with the defaults;
            20 attempts at growth 5 reach 1.9e7).

    """

    initial: float = 1e-6
    growth: float = 10.0
    max_shifts: int = 14

    def __post_init__(self) -> None:
        if not self.initial > 0:
            raise InputError(f"ShiftOptions.initial: must be > 0, got {self.initial!r}")
        if not self.growth > 1:
            raise InputError(f"ShiftOptions.growth: must be > 1, got {self.growth!r}")
        if self.max_shifts < 1:
            raise InputError(f"ShiftOptions.max_shifts: must be >= 1, got {self.max_shifts!r}")

    def schedule(self, diagonal_scale: float, start: float = 0.0) -> np.ndarray:
        """Absolute shifts to try: ``max(initial * scale, start) * growth**j``."""
        tau0 = max(self.initial * diagonal_scale, start)
        return tau0 * self.growth ** np.arange(self.max_shifts)


@dataclass(frozen=True)
class FactorReport:
    """Outcome of one numeric factorisation.

    Attributes:
        success: False if the backend reported a failure (MUMPS INFOG(1) < 0, zero pivot,
            singular factor).
        reason: "ok" or the backend's diagnostic.
        negative_pivots: Number of negative pivots of a symmetric factorisation (= negative
            eigenvalues); None when the backend cannot tell (LU).
        expected_negative: Negative pivots that are expected (the ``-I`` block of the
            augmented system); more than that means the matrix is indefinite.
        analysis_time: Seconds in the symbolic analysis (0 when it was reused).
        numeric_time: Seconds in the numeric factorisation.
        reused_analysis: True when the symbolic analysis of an earlier call was reused (MUMPS,
            PETSc; always False for SuperLU_DIST, which logs no separate symbolic phase and
            only keeps its column ordering, and for scipy).
        shift: Diagonal shift tau added before this factorisation (0 = none).
        factor_nnz: Entries in the factors (MUMPS INFOG(29), PETSc MatGetInfo nz_used, scipy
            nnz(L) + nnz(U)); None when unknown.
        memory_mb: Memory of the factorisation in MB (MUMPS INFOG(22)); None when unknown.
        factor_flops: Floating-point operations of the elimination its analysis estimated
            (MUMPS RINFOG(1): set by the pattern and the ordering alone); None when unknown.

    """

    success: bool
    reason: str = "ok"
    negative_pivots: int | None = None
    expected_negative: int = 0
    analysis_time: float = 0.0
    numeric_time: float = 0.0
    reused_analysis: bool = False
    shift: float = 0.0
    factor_nnz: int | None = None
    memory_mb: float | None = None
    factor_flops: float | None = None

    @property
    def indefinite(self) -> bool | None:
        """True if more negative pivots than expected were found; None when unknown."""
        if self.negative_pivots is None:
            return None
        return self.negative_pivots > self.expected_negative

    @property
    def usable_spd(self) -> bool:
        """Succeeded and not known to be indefinite (usable as an SPD Newton matrix)."""
        return self.success and not self.indefinite


class _Backend(Protocol):
    """What :class:`SparseDirectSolver` needs from a backend."""

    def update(self, data: np.ndarray) -> None:
        """Replace the matrix values (same pattern)."""

    def factorize(self) -> FactorReport:
        """Numeric (and the first time, symbolic) factorisation."""

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve with the current factor."""

    def destroy(self) -> None:
        """Free the factor (and PETSc objects)."""


def _check_pattern_csr(matrix: sp.spmatrix, name: str = "matrix") -> sp.csr_matrix:
    """Square CSR with sorted, duplicate-free indices, or InputError."""
    if not sp.issparse(matrix) or matrix.shape[0] != matrix.shape[1]:
        raise InputError(f"{name}: expected a square scipy sparse matrix, got "
                         f"{type(matrix).__name__} {getattr(matrix, 'shape', None)}")
    a = sp.csr_matrix(matrix)
    if not a.has_canonical_format:
        a = a.copy()
        a.sum_duplicates()
    return a


def pattern_data(matrix: sp.spmatrix, pattern: sp.csr_matrix, name: str) -> np.ndarray:
    """Return the data of ``matrix`` (canonical CSR) if it has exactly ``pattern``'s structure.

    Raises:
        InputError: the structure differs (a new pattern needs a new solver).

    """
    a = _check_pattern_csr(matrix, name) if matrix.shape[0] == matrix.shape[1] \
        else sp.csr_matrix(matrix)
    if a.indptr is pattern.indptr and a.indices is pattern.indices:
        return a.data
    if a.shape != pattern.shape or a.nnz != pattern.nnz or not (
            np.array_equal(a.indptr, pattern.indptr)
            and np.array_equal(a.indices, pattern.indices)):
        raise InputError(f"{name}: sparsity pattern differs from the pattern the solver was "
                         "built with")
    return a.data


def _upper_block_positions(pattern: sp.csr_matrix, bs: int) -> tuple[np.ndarray, ...]:
    """Block-CSR pattern of the upper block triangle and where each value comes from.

    Returns ``(bindptr, bindices, source)``: ``source[k]`` is the position in ``pattern.data``
    of the k-th value of the row-major ``bs x bs`` blocks (or -1 for an entry outside the
    pattern, which stays zero).
    """
    n = pattern.shape[0]
    if n % bs:
        raise InputError(f"matrix: size {n} is not a multiple of the block size {bs}")
    marker = sp.csr_matrix((np.arange(1, pattern.nnz + 1, dtype=np.float64),
                            pattern.indices, pattern.indptr), shape=pattern.shape)
    rows = np.repeat(np.arange(n), np.diff(pattern.indptr))
    keep = pattern.indices // bs >= rows // bs
    upper = sp.csr_matrix((marker.data[keep], (rows[keep], pattern.indices[keep])),
                          shape=pattern.shape)
    bsr = upper.tobsr(blocksize=(bs, bs))
    bsr.sort_indices()
    # MatSetValuesBlocked reads a block row as one (bs x k bs) array; column-oriented input
    # (MAT_ROW_ORIENTED = false) makes that block after block, each stored transposed.
    source = bsr.data.transpose(0, 2, 1).reshape(-1).astype(np.int64) - 1
    return bsr.indptr.astype(PETSc.IntType), bsr.indices.astype(PETSc.IntType), source


def set_mumps_controls(factor: Any, opts: LinearSolverOptions) -> None:
    """ICNTL(7) ordering, ICNTL(35) BLR (+ CNTL(7)), ICNTL(10), ICNTL(22), then user ICNTLs.

    Shared by the serial backend and the distributed solves (solvers/decomposition).
    """
    factor.setMumpsIcntl(7, MUMPS_ORDERINGS[opts.resolved_ordering])
    factor.setMumpsIcntl(35, 1 if opts.mumps_blr else 0)
    if opts.mumps_blr:
        factor.setMumpsCntl(7, opts.mumps_blr_tolerance)
    factor.setMumpsIcntl(10, opts.mumps_refinement)
    factor.setMumpsIcntl(22, 1 if opts.mumps_out_of_core else 0)
    for index, value in opts.mumps_icntl:
        factor.setMumpsIcntl(int(index), int(value))


def factor_ksp(mat: Any, options: LinearSolverOptions, comm: Any,
               mumps_icntl: tuple[tuple[int, int], ...] | None = None) -> Any:
    """KSPPREONLY + PCFactor of ``options.backend`` on ``mat`` (serial and distributed solves).

    LU for ``options.symmetric == "lu"``, else Cholesky (MUMPS: LDL^T unless ``mat`` is
    flagged SPD). With ``mumps_icntl`` (MUMPS only) the factor matrix is created at once and
    gets these ``(index, value)`` controls, then :func:`set_mumps_controls`; without, the
    package's defaults apply (a caller that sets package options first then calls
    ``pc.setFactorSetUpSolverType()`` itself).
    """
    ksp = PETSc.KSP().create(comm=comm)
    ksp.setOperators(mat)
    ksp.setType(PETSc.KSP.Type.PREONLY)
    pc = ksp.getPC()
    pc.setType("lu" if options.symmetric == "lu" else "cholesky")
    pc.setFactorSolverType(options.backend)
    if mumps_icntl is not None:
        pc.setFactorSetUpSolverType()
        factor = pc.getFactorMatrix()
        for index, value in mumps_icntl:
            factor.setMumpsIcntl(index, value)
        set_mumps_controls(factor, options)
    return ksp


def coo_aij(comm: Any, local: int, total: int, rows: np.ndarray, cols: np.ndarray) -> Any:
    """Symmetric AIJ ``total x total`` with ``local`` rows on this rank, COO pattern given.

    ``rows`` / ``cols`` are global indices of this rank's entries; the pattern is set once
    (``MatSetPreallocationCOO``), so ``setValuesCOO`` keeps the nonzero state and the
    factorisation's symbolic analysis is reused.
    """
    mat: Any = PETSc.Mat().create(comm=comm)
    mat.setSizes(((local, total), (local, total)))
    mat.setType(PETSc.Mat.Type.AIJ)
    mat.setPreallocationCOO(rows.astype(PETSc.IntType), cols.astype(PETSc.IntType))
    mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    return mat


def factor_event_totals(symmetric: str) -> tuple[tuple[float, int], tuple[float, int]]:
    """(time, count) of PETSc's symbolic and numeric factorisation log events so far."""
    infos = [PETSc.Log.Event(name).getPerfInfo() for name in _FACTOR_EVENTS[symmetric]]
    return (infos[0]["time"], infos[0]["count"]), (infos[1]["time"], infos[1]["count"])


def factor_status(pc: Any, failed: int, error: str,
                  options: LinearSolverOptions) -> tuple[bool, int | None, str]:
    """Success, negative pivots and reason of the factorisation :func:`setup_pc` ran.

    ``failed`` / ``error`` are :func:`setup_pc`'s. MUMPS: ``INFOG(1) < 0`` is a failure
    (reason with ``INFOG(2)``), the negative pivots are ``INFOG(12)`` (not for LU); PETSc
    Cholesky: the inertia's negative count.
    """
    if failed == -1:
        return False, None, error
    factor = pc.getFactorMatrix()
    if options.backend == "mumps":
        infog1 = factor.getMumpsInfog(1)
        if infog1 < 0:
            return False, None, f"MUMPS INFOG(1)={infog1}, INFOG(2)={factor.getMumpsInfog(2)}"
        negatives = None if options.symmetric == "lu" else factor.getMumpsInfog(12)
    elif options.backend == "petsc" and options.symmetric == "cholesky":
        negatives = int(factor.getInertia()[0]) if failed == 0 else None
    else:
        negatives = None
    if failed != 0:
        return False, negatives, f"PCFailedReason {failed} (zero pivot / breakdown)"
    return True, negatives, "ok"


class _PetscBackend:
    """PCFactor (MUMPS / PETSc / SuperLU_DIST) on a matrix built once."""

    def __init__(self, pattern: sp.csr_matrix, options: LinearSolverOptions,
                 expected_negative: int) -> None:
        self.options = options
        self.expected_negative = expected_negative
        self.n = pattern.shape[0]
        self.mat = self._create_matrix(pattern)
        self.ksp = self._create_ksp()
        self.rhs, self.sol = self.mat.createVecs()
        self.factorizations = 0

    def _create_matrix(self, pattern: sp.csr_matrix) -> Any:
        """AIJ wrapping the CSR arrays, or SBAIJ (bs=3) of the upper block triangle."""
        if self.options.matrix_format == "sbaij":
            self._bindptr, self._bindices, self._source = _upper_block_positions(
                pattern, BLOCK_SIZE)
            self._bvalues = np.zeros(self._source.size)
            mat: Any = PETSc.Mat()
            mat.createSBAIJ((self.n, self.n), BLOCK_SIZE,
                            csr=(self._bindptr, self._bindices, self._bvalues),
                            comm=PETSc.COMM_SELF)
            mat.setOption(PETSc.Mat.Option.ROW_ORIENTED, False)
        else:
            # no copy when the pattern is already int32 (PETSc.IntType): the constant shell
            # pattern arrays are shared, not duplicated (0.3 GB of indices at 640k vertices)
            self._indptr = pattern.indptr.astype(PETSc.IntType, copy=False)
            self._indices = pattern.indices.astype(PETSc.IntType, copy=False)
            self._values = np.zeros(pattern.nnz, dtype=PETSc.ScalarType)
            mat = PETSc.Mat()
            mat.createAIJWithArrays(
                (self.n, self.n), (self._indptr, self._indices, self._values),
                comm=PETSc.COMM_SELF)
        mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        mat.setOption(PETSc.Mat.Option.SPD, self.options.symmetric == "cholesky")
        mat.assemble()
        return mat

    def _create_ksp(self) -> Any:
        """KSPPREONLY + PCFactor of the chosen backend, ordering and MUMPS controls."""
        opts = self.options
        if opts.backend == "mumps":
            return factor_ksp(self.mat, opts, PETSc.COMM_SELF, mumps_icntl=())
        ksp = factor_ksp(self.mat, opts, PETSc.COMM_SELF)
        pc = ksp.getPC()
        if opts.backend == "petsc":
            pc.setFactorOrdering(opts.resolved_ordering)
        elif opts.backend == "superlu_dist":
            prefix = f"wrinkles_sld{id(self)}_"
            ksp.setOptionsPrefix(prefix)
            PETSc.Options().setValue(f"{prefix}mat_superlu_dist_colperm", opts.resolved_ordering)
            ksp.setFromOptions()
        pc.setFactorSetUpSolverType()  # creates the factor matrix, which reads the options
        if opts.backend == "superlu_dist":
            PETSc.Options().delValue(f"{ksp.getOptionsPrefix()}mat_superlu_dist_colperm")
        return ksp

    def update(self, data: np.ndarray) -> None:
        """Copy new values in place; the nonzero state is unchanged (analysis is reused)."""
        if self.options.matrix_format == "sbaij":
            valid = self._source >= 0
            self._bvalues[valid] = data[self._source[valid]]
            self.mat.setValuesBlockedCSR(self._bindptr, self._bindices, self._bvalues)
            self.mat.assemble()
        else:
            np.copyto(self._values, data)
            self.mat.stateIncrease()

    def factorize(self) -> FactorReport:
        """PCSetUp; time the phases from PETSc's log events; read MUMPS / inertia info."""
        pc = self.ksp.getPC()
        (sym0, nsym0), _ = factor_event_totals(self.options.symmetric)
        failed, error, total = setup_pc(pc)
        (sym1, nsym1), _ = factor_event_totals(self.options.symmetric)
        self.factorizations += 1
        analysis = sym1 - sym0
        # SuperLU_DIST logs no symbolic event and only keeps its column ordering
        # (Fact = SamePattern): it is never reported as reusing the analysis
        reused = (nsym1 == nsym0 and self.factorizations > 1
                  and self.options.backend != "superlu_dist")
        success, negatives, reason = factor_status(pc, failed, error, self.options)
        nnz, memory = self._factor_size(pc) if success else (None, None)
        flops = (float(pc.getFactorMatrix().getMumpsRinfog(1))
                 if success and self.options.backend == "mumps" else None)
        if not success:
            # PCSetUp skips the numeric phase while the factor keeps its error flag (petsc4py
            # has no MatFactorClearError): start again from a fresh KSP, which costs one new
            # symbolic analysis after a failure only
            self.ksp.destroy()
            self.ksp = self._create_ksp()
            self.factorizations = 0
        return FactorReport(success=success, reason=reason,
                            negative_pivots=negatives, expected_negative=self.expected_negative,
                            analysis_time=analysis, numeric_time=total - analysis,
                            reused_analysis=reused, factor_nnz=nnz, memory_mb=memory,
                            factor_flops=flops)

    def _factor_size(self, pc: Any) -> tuple[int | None, float | None]:
        """(entries in the factors, MB) from MUMPS INFOG(29)/(22) or PETSc MatGetInfo."""
        factor = pc.getFactorMatrix()
        if self.options.backend == "mumps":
            entries = factor.getMumpsInfog(29)  # negative: millions of entries
            return (entries if entries >= 0 else -entries * 1_000_000), \
                float(factor.getMumpsInfog(22))
        if self.options.backend == "petsc":
            return int(factor.getInfo()["nz_used"]), None
        return None, None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Forward/backward substitution with the current factor."""
        self.rhs.setArray(rhs)
        self.ksp.solve(self.rhs, self.sol)
        return self.sol.getArray().copy()

    def destroy(self) -> None:
        """Destroy the KSP (with its factor), the matrix and the work vectors."""
        for obj in (self.ksp, self.mat, self.rhs, self.sol):
            obj.destroy()


class _ScipyBackend:
    """scipy SuperLU (``splu``): LU, or symmetric mode with inertia for cholesky/ldlt."""

    def __init__(self, pattern: sp.csr_matrix, options: LinearSolverOptions,
                 expected_negative: int) -> None:
        self.options = options
        self.expected_negative = expected_negative
        self.matrix = pattern.copy()
        self.lu: Any = None

    def update(self, data: np.ndarray) -> None:
        """Copy the new values into the stored CSR."""
        np.copyto(self.matrix.data, data)

    def _splu_kwargs(self) -> dict[str, Any]:
        """Symmetric mode (diag pivoting, A^T + A ordering) unless plain LU was asked."""
        kwargs: dict[str, Any] = {"permc_spec": self.options.resolved_ordering}
        if self.options.symmetric != "lu":
            kwargs.update(diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        return kwargs

    def factorize(self) -> FactorReport:
        """Full splu (scipy cannot keep the analysis); inertia from diag(U) when symmetric."""
        start = time.perf_counter()
        try:
            self.lu = sla.splu(self.matrix.tocsc(), **self._splu_kwargs())
        except RuntimeError as err:
            self.lu = None
            return FactorReport(success=False, reason=f"splu: {err}",
                                expected_negative=self.expected_negative,
                                numeric_time=time.perf_counter() - start)
        elapsed = time.perf_counter() - start
        diag = self.lu.U.diagonal()
        ok = bool(np.all(np.isfinite(diag)) and np.all(diag != 0))
        return FactorReport(success=ok, reason="ok" if ok else "zero or non-finite pivot",
                            negative_pivots=self._negative_pivots(diag),
                            expected_negative=self.expected_negative, numeric_time=elapsed,
                            factor_nnz=int(self.lu.L.nnz + self.lu.U.nnz))

    def _negative_pivots(self, diag: np.ndarray) -> int | None:
        """Sign count of diag(U) when the row and column permutations agree (symmetric)."""
        if self.options.symmetric == "lu" or not np.array_equal(self.lu.perm_r, self.lu.perm_c):
            return None
        return int(np.count_nonzero(diag < 0))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Triangular solves with the SuperLU factor."""
        return np.asarray(self.lu.solve(rhs), dtype=np.float64)

    def destroy(self) -> None:
        """Drop the SuperLU factor."""
        self.lu = None


@dataclass
class SolverStats:
    """Accumulated counts and wall times of a :class:`SparseDirectSolver` (seconds)."""

    factorizations: int = 0
    analysis_time: float = 0.0
    numeric_time: float = 0.0
    solves: int = 0
    solve_time: float = 0.0
    history: list[FactorReport] = field(default_factory=list)


def setup_pc(pc: Any) -> tuple[int, str, float]:
    """``PCSetUp`` (factorise) timed: ``(failed, reason, seconds)``.

    ``failed`` is PETSc's PCFailedReason (0 = ok), or -1 when PETSc raised (``reason`` then
    names the error code).
    """
    start = time.perf_counter()
    reason = "ok"
    try:
        pc.setUp()
        failed = int(pc.getFailedReason())
    except PETSc.Error as err:
        failed, reason = -1, f"PETSc error {getattr(err, 'ierr', err)}"
    return failed, reason, time.perf_counter() - start


class SparseDirectSolver:
    """Direct solver for a fixed-pattern symmetric sparse matrix (the shell Hessian).

    Build it once from the pattern; then ``factorize(A)`` with any matrix of the same pattern
    (values only are copied; the symbolic analysis is reused) and ``solve(b)``.

    Args:
        pattern: Square scipy sparse matrix whose pattern (indptr, indices) all later
            matrices share; it must contain the diagonal for :meth:`factorize_shifted`.
        options: Backend, factorisation, ordering.
        expected_negative: Negative pivots that do not mean indefiniteness (augmented system).

    """

    def __init__(self, pattern: sp.spmatrix, options: LinearSolverOptions | None = None,
                 expected_negative: int = 0) -> None:
        self.options = options or LinearSolverOptions()
        self.pattern = _check_pattern_csr(pattern, "SparseDirectSolver.pattern")
        self.n = self.pattern.shape[0]
        self.diagonal_positions = diagonal_positions(self.pattern)
        make = _ScipyBackend if self.options.backend == "scipy" else _PetscBackend
        self._backend: _Backend = make(self.pattern, self.options, expected_negative)
        self.stats = SolverStats()

    def _values_of(self, matrix: sp.spmatrix) -> np.ndarray:
        """Return the data array of ``matrix`` in the stored pattern's order, or InputError."""
        return pattern_data(matrix, self.pattern, "SparseDirectSolver.factorize: matrix")

    def factorize(self, matrix: sp.spmatrix, shift: float = 0.0) -> FactorReport:
        """Numeric factorisation of ``matrix + shift I`` (symbolic analysis reused).

        Args:
            matrix: Same pattern as the constructor's.
            shift: Diagonal shift tau >= 0.

        Returns:
            The :class:`FactorReport` (also appended to ``stats.history``).

        """
        values = self._values_of(matrix)  # the backend copies it: no persistent copy here
        if shift:
            if self.diagonal_positions is None:
                raise InputError("SparseDirectSolver.pattern: a diagonal shift needs every "
                                 "diagonal entry in the pattern")
            values = values.copy()
            values[self.diagonal_positions] += shift
        self._backend.update(values)
        report = replace(self._backend.factorize(), shift=float(shift))
        self._record(report)
        return report

    def _record(self, report: FactorReport) -> None:
        """Accumulate a factorisation into ``stats``."""
        self.stats.factorizations += 1
        self.stats.analysis_time += report.analysis_time
        self.stats.numeric_time += report.numeric_time
        self.stats.history.append(report)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve ``A x = rhs`` with the last factorisation."""
        b = np.ascontiguousarray(rhs, dtype=np.float64)
        if b.shape != (self.n,):
            raise InputError(f"SparseDirectSolver.solve: rhs shape {b.shape}, expected "
                             f"({self.n},)")
        start = time.perf_counter()
        x = self._backend.solve(b)
        self.stats.solves += 1
        self.stats.solve_time += time.perf_counter() - start
        return x

    def destroy(self) -> None:
        """Free the factorisation and the PETSc objects now (not at garbage collection)."""
        self._backend.destroy()

    def factorize_shifted(self, matrix: sp.spmatrix, shift: ShiftOptions,
                          start: float = 0.0) -> list[FactorReport]:
        """Factorise ``matrix``; if it fails or is indefinite retry ``matrix + tau I``.

        Returns every attempt; the last one is the factor in use (check ``usable_spd``).
        """
        data = self._values_of(matrix)
        scale = _mean_abs(data[self.diagonal_positions]) if self.diagonal_positions is not None \
            else 1.0
        return factorize_with_shift(lambda tau: self.factorize(matrix, tau), scale, shift, start)


ORDERING_CANDIDATES: tuple[str, ...] = ("metis", "amf")
"""MUMPS orderings :func:`cheapest_ordering` compares: nested dissection and approximate
minimum fill (docs/notes/phase-space.md)."""


def cheapest_ordering(matrix: sp.spmatrix, options: LinearSolverOptions,
                      ) -> tuple[SparseDirectSolver, FactorReport]:
    """Build a solver for ``matrix``'s pattern in the ordering of the fewest factor flops.

    ``matrix`` is factorised once in each of :data:`ORDERING_CANDIDATES`; the solver of the
    smallest analysis estimate (``FactorReport.factor_flops``, MUMPS RINFOG(1): a function of
    the pattern and the ordering, so every rank holding the same pattern chooses alike) is
    kept, factorised, and the others are destroyed. A backend other than MUMPS, or an
    ordering named in ``options``, is factorised as asked. The one-off cost is one extra
    factorisation; it pays where the same pattern is factorised many times (the phase
    space's ``A_Z`` at every Newton matrix), and no ordering wins on every pattern: on the
    shipped shells METIS or AMF is the cheaper by up to 1.5x in flops.

    Returns:
        The chosen solver and the report of its factorisation of ``matrix``.

    """
    if options.backend != "mumps" or options.ordering:
        solver = SparseDirectSolver(matrix, options)
        return solver, solver.factorize(matrix)
    tried = []
    for ordering in ORDERING_CANDIDATES:
        solver = SparseDirectSolver(matrix, replace(options, ordering=ordering))
        tried.append((solver, solver.factorize(matrix)))
    costs = [r.factor_flops if r.success and r.factor_flops is not None else np.inf
             for _, r in tried]
    best = int(np.argmin(costs))
    for k, (solver, _) in enumerate(tried):
        if k != best:
            solver.destroy()
    return tried[best]


def _mean_abs(values: np.ndarray) -> float:
    """Mean absolute value, or 1 when it is zero (a scale for relative shifts)."""
    scale = float(np.mean(np.abs(values))) if values.size else 0.0
    return scale if scale > 0 else 1.0


def shift_candidates(diagonal_scale: float, shift: ShiftOptions, start: float = 0.0,
                     zero_first: bool | None = None) -> list[float]:
    """Shifts to try, in order: the one schedule of every shifted factorisation.

    ``max(tau_0, start) growth^j`` (``tau_0 = initial * diagonal_scale``, j < max_shifts),
    preceded by ``0`` (the unshifted matrix) when ``zero_first``, by default when
    ``start < tau_0``. The shell Newton passes ``start = tau_prev / decay`` after an iteration
    that needed ``tau_prev``; far from the minimum with ``zero_first = False``, so it reuses
    the last successful shift instead of paying again for the failed ``0`` and
    ``tau_prev / growth`` attempts (the shift returns to 0 once it decays below ``tau_0``).
    """
    tau0 = shift.initial * diagonal_scale
    shifts = shift.schedule(diagonal_scale, start).tolist()
    return [0.0, *shifts] if (start < tau0 if zero_first is None else zero_first) else shifts


def factorize_with_shift(factorize: Callable[[float], FactorReport], diagonal_scale: float,
                         shift: ShiftOptions, start: float = 0.0,
                         accept: Callable[[FactorReport], bool] | None = None,
                         zero_first: bool | None = None,
                         restart: Callable[[FactorReport, list[float]], list[float]] | None
                         = None) -> list[FactorReport]:
    """Call ``factorize(tau)`` for the shifts of :func:`shift_candidates` until one is accepted.

    By default a factorisation is accepted when it succeeded and is not indefinite (Nocedal &
    Wright Alg. 3.3); the shell Newton passes an ``accept`` that also solves and line-searches
    (a direction that is not a descent direction or fails the line search moves on to the next
    shift). With ``restart``, a first attempt whose factorisation is indefinite replaces the
    remaining shifts by ``restart(report, remaining)``'s (those above that attempt; none keeps
    the ladder; :mod:`solvers.inertia_shift`).
    Returns every attempt, the last one being the factor left in the solver.
    """
    ok = accept or (lambda report: report.usable_spd)
    reports: list[FactorReport] = []
    candidates = shift_candidates(diagonal_scale, shift, start, zero_first)
    i = 0
    while i < len(candidates):
        tau = float(candidates[i])
        i += 1
        reports.append(factorize(tau))
        if ok(reports[-1]):
            break
        if restart is not None and len(reports) == 1 and reports[0].indefinite:
            fresh = [t for t in restart(reports[0], candidates[i:]) if t > tau]
            if fresh:
                candidates, i = fresh, 0
    return reports


class DiagonalScale:
    """Mean ``|A_ii|`` (the shift ladder's scale) and diagonals of matrices of one CSR pattern.

    The diagonal's positions in the values are found once per pattern instead of a search of
    every row per call. A pattern is recognised by the buffers its index arrays live in and
    its size (the shell assembly's Hessians share their arrays, a rank's Hessian rows are
    views of them); the arrays are kept referenced while they are the cached pattern, so a
    buffer cannot be freed and reused by another one. A pattern without the full diagonal
    uses scipy's ``diagonal()`` (missing entries are zeros).
    """

    def __init__(self) -> None:
        self._pattern: tuple[Any, ...] | None = None
        self._positions: np.ndarray | None = None

    def diagonal(self, csr: sp.csr_matrix) -> np.ndarray:
        """Return ``A_ii`` of every row i (a rectangular matrix: its leading square part)."""
        key = (csr.indptr.ctypes.data, csr.indices.ctypes.data, csr.shape, csr.nnz)
        if self._pattern is None or self._pattern[:4] != key:
            self._pattern = (*key, csr.indptr, csr.indices)
            self._positions = diagonal_positions(csr)
        return np.asarray(csr.data[self._positions] if self._positions is not None
                          else csr.diagonal())

    def __call__(self, matrix: Any) -> float:
        """Return ``mean |diag(matrix)|``, or 1 when that is 0 (NaN stays NaN).

        ``matrix``: scipy sparse, or any object with ``diagonal()`` (a rank's owned rows).
        """
        if not sp.issparse(matrix):
            return float(np.mean(np.abs(matrix.diagonal()))) or 1.0
        diagonal = self.diagonal(matrix if sp.isspmatrix_csr(matrix) else sp.csr_matrix(matrix))
        return float(np.mean(np.abs(diagonal))) or 1.0


def diagonal_positions(pattern: sp.csr_matrix) -> np.ndarray | None:
    """Position of each diagonal entry ``(i, i)`` in ``pattern.data``, or None if one is missing.

    Row i of a rectangular pattern (a rank's leading rows) has its diagonal at column i.
    """
    n = pattern.shape[0]
    rows = np.repeat(np.arange(n), np.diff(pattern.indptr))
    pos = np.flatnonzero(rows == pattern.indices)
    return pos if pos.size == n else None


def true_residual(matrix: sp.spmatrix, x: np.ndarray, rhs: np.ndarray) -> float:
    """Relative true residual ``||A x - b|| / ||b||`` (the check MISSION.md section 6 asks)."""
    norm_b = float(np.linalg.norm(rhs))
    return float(np.linalg.norm(matrix @ x - rhs)) / (norm_b if norm_b > 0 else 1.0)


def _marked(matrix: sp.csr_matrix, offset: int) -> sp.csr_matrix:
    """Copy of ``matrix`` whose values are ``offset + 1 + position`` (exact in float64)."""
    ids = np.arange(offset + 1, offset + 1 + matrix.nnz, dtype=np.float64)
    return sp.csr_matrix((ids, matrix.indices, matrix.indptr), shape=matrix.shape)


@dataclass(frozen=True)
class _AugmentedLayout:
    """Pattern of K = [[A, G^T], [G, -I]] and where A's and G's values go in K.data."""

    pattern: sp.csr_matrix
    from_a: np.ndarray
    to_a: np.ndarray
    from_g: np.ndarray
    to_g: np.ndarray
    to_gt: np.ndarray
    from_gt: np.ndarray
    to_identity: np.ndarray


def augmented_layout(a_pattern: sp.csr_matrix, g_pattern: sp.csr_matrix) -> _AugmentedLayout:
    """Assemble the block pattern once; record index maps so updates are gathers.

    Each block is filled with unique integer markers, ``scipy.sparse.bmat`` assembles them,
    and the markers found in K.data tell where every A / G / G^T / -I value lands.
    """
    n, m = a_pattern.shape[0], g_pattern.shape[0]
    if g_pattern.shape[1] != n:
        raise InputError(f"penalty_factor: G has {g_pattern.shape[1]} columns, A has {n} rows")
    ma, mg = _marked(a_pattern, 0), _marked(g_pattern, a_pattern.nnz)
    ident = sp.identity(m, format="csr") * float(a_pattern.nnz + g_pattern.nnz + 1)
    k = sp.bmat([[ma, mg.T.tocsr()], [mg, ident]], format="csr")
    k.sort_indices()
    ids = k.data.astype(np.int64) - 1
    in_a = ids < a_pattern.nnz
    in_i = ids == a_pattern.nnz + g_pattern.nnz
    in_g = ~in_a & ~in_i
    rows = np.repeat(np.arange(k.shape[0]), np.diff(k.indptr))
    g_below = in_g & (rows >= n)
    g_right = in_g & (rows < n)
    pattern = sp.csr_matrix((np.zeros(k.nnz), k.indices.copy(), k.indptr.copy()),
                            shape=k.shape)
    return _AugmentedLayout(pattern, ids[in_a], np.flatnonzero(in_a),
                            ids[g_below] - a_pattern.nnz, np.flatnonzero(g_below),
                            np.flatnonzero(g_right), ids[g_right] - a_pattern.nnz,
                            np.flatnonzero(in_i))


class AugmentedPenaltySolver:
    """Solve ``(A + G^T G) dx = b`` through ``[[A, G^T], [G, -I]] [dx; mu] = [b; 0]``.

    Eliminating ``mu = G dx`` gives back ``(A + G^T G) dx = b``. The augmented matrix is
    quasi-definite when A is SPD, with exactly ``m = rows(G)`` negative eigenvalues (Haynsworth
    inertia additivity: In(K) = In(-I) + In(A + G^T G)); more negative pivots than m mean
    ``A + G^T G`` is indefinite. Needs a symmetric indefinite factorisation: "ldlt" (mumps) or
    "lu".

    Args:
        a_pattern: Pattern of A (3n x 3n), containing the diagonal.
        g_pattern: Pattern of G (m x 3n).
        options: Linear solver options (``symmetric`` must be "ldlt" or "lu").

    """

    def __init__(self, a_pattern: sp.spmatrix, g_pattern: sp.spmatrix,
                 options: LinearSolverOptions | None = None) -> None:
        opts = options or LinearSolverOptions(symmetric="ldlt")
        if opts.symmetric == "cholesky":
            raise InputError("LinearSolverOptions.symmetric: the augmented penalty system is "
                             "indefinite; use 'ldlt' or 'lu', not 'cholesky'")
        self.a_pattern = _check_pattern_csr(a_pattern, "AugmentedPenaltySolver.a_pattern")
        self.g_pattern = sp.csr_matrix(g_pattern)
        self.g_pattern.sum_duplicates()
        self.layout = augmented_layout(self.a_pattern, self.g_pattern)
        self.n, self.m = self.a_pattern.shape[0], self.g_pattern.shape[0]
        self.solver = SparseDirectSolver(self.layout.pattern, opts, expected_negative=self.m)
        self._k = self.layout.pattern.copy()
        self._k.data[self.layout.to_identity] = -1.0
        self.a_diagonal = diagonal_positions(self.a_pattern)

    def assemble(self, a: sp.spmatrix, g: sp.spmatrix, shift: float = 0.0) -> sp.csr_matrix:
        """Fill and return K for values ``a``, ``g`` (``shift`` added on A's diagonal)."""
        a_data = pattern_data(a, self.a_pattern, "AugmentedPenaltySolver: A").copy()
        if shift:
            a_data[self.a_diagonal] += shift
        g_data = pattern_data(g, self.g_pattern, "AugmentedPenaltySolver: G")
        lay = self.layout
        self._k.data[lay.to_a] = a_data[lay.from_a]
        self._k.data[lay.to_g] = g_data[lay.from_g]
        self._k.data[lay.to_gt] = g_data[lay.from_gt]
        return self._k

    def factorize(self, a: sp.spmatrix, g: sp.spmatrix, shift: float = 0.0) -> FactorReport:
        """Factorise the augmented matrix (A + shift I on the top-left block)."""
        return self.solver.factorize(self.assemble(a, g, shift))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``dx`` with ``(A + G^T G) dx = rhs`` from the current factor."""
        full = np.concatenate([np.asarray(rhs, dtype=np.float64), np.zeros(self.m)])
        return self.solver.solve(full)[: self.n]

    def destroy(self) -> None:
        """Free the factorisation of the augmented matrix."""
        self.solver.destroy()

    def factorize_shifted(self, a: sp.spmatrix, g: sp.spmatrix,
                          shift: ShiftOptions, start: float = 0.0) -> list[FactorReport]:
        """Like :meth:`SparseDirectSolver.factorize_shifted`, shifting only the A block."""
        scale = _mean_abs(sp.csr_matrix(a).diagonal())
        return factorize_with_shift(lambda tau: self.factorize(a, g, tau), scale, shift, start)
