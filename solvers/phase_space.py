"""Wrinkle-phase coarse space: a second coarse correction for the soft band of a wrinkled shell.

Near a wrinkled minimum the multigrid-preconditioned shell Newton matrix has a band of soft
modes: compression balances bending, so shifting the wrinkles sideways costs almost nothing.
Such a mode is a smooth envelope times the wrinkle carrier, ``a(X) d_X w``: oscillatory at the
fine scale yet of low energy, the near-kernel of a Helmholtz-like operator. The remedy follows
the wave-ray idea (Brandt & Livshits, SIAM J. Sci. Comput. 18, 1997) and the local coarse
spaces of spectral AMGe / GenEO: the carrier modulated by coarse hats.

The basis: with ``d = x - y`` the wrinkle displacement (positions minus the penalty target),
``D_k`` the surface gradient along the ambient rest direction ``e_k`` (:func:`surface_gradients`)
and ``(u_j, v_j)`` a tangent frame at coarse hat j (:func:`hat_frames`), the test fields of hat j
are

    t_0 = d,  t_1 = sum_k u_jk D_k d,  t_2 = sum_k v_jk D_k d        (n, 3) each,

the wrinkles and their phase-shifted partners; the columns are every coarse hat ``phi_j``
(vertex hats of hierarchy level ``phase_level``, the product of the subdivision matrices from
there to the shell) times its test fields:

    Z[3 v + c, 3 j + m] = phi_j(v) t_m[v, c] / ||column||,

so ``span Z`` holds every coarse-scale modulation of the amplitude and phase of the wrinkles
(the per-hat frame keeps two independent derivatives, ``n . grad = 0``). Z's pattern is fixed
(the hats'); its values follow x every Newton iteration. The coarse matrix
``A_Z = Z^T (A + tau I + G^T G) Z`` (``Z^T A Z`` over 3 x 3 vertex blocks, on ranks each
rank's rows summed, plus ``tau Z^T Z`` and ``(G Z)^T (G Z)``) is factorised by MUMPS LDL^T
(ordering: :func:`solvers.linear.cheapest_ordering`); its inertia tells whether it is
positive definite (else the multigrid runs alone for that matrix: ``Z^T A Z`` indefinite means
A is). A zero column (no wrinkles under a hat) keeps a unit diagonal: the pattern never changes.

The correction enters CG as the deflation preconditioner A-DEF2 of Tang, Nabben, Vuik &
Erlangga (J. Sci. Comput. 39, 2009), ``P = M + Q (I - A M)`` with ``Q = Z A_Z^{-1} Z^T`` and M
the multigrid V-cycle, from the start ``x_0 = Q b``: the CG residuals then satisfy
``Z^T r = 0``, where P equals the symmetric balancing preconditioner
``Q + (I - QA) M (I - AQ)`` (Mandel, Commun. Numer. Methods Eng. 9, 1993). One application is
one V-cycle, one product with A and one coarse solve.

Measurements (CG iterations, time per Newton iteration): docs/notes/phase-space.md.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import PETSc
from models.shell.rest import area_weighted_normals
from solvers.block_galerkin import entry_keys
from solvers.block_phase import BlockPhaseProduct, TransposeBlockProduct
from solvers.linear import (
    FactorReport,
    LinearSolverOptions,
    SparseDirectSolver,
    cheapest_ordering,
)

TEST_FIELDS: int = 3
"""Test fields per hat: the wrinkle displacement and its derivatives along the hat's two
tangent directions."""


def surface_gradients(vertices: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, ...]:
    """Vertex surface-gradient operators ``(D_1, D_2, D_3)`` of the P1 field on a triangle mesh.

    On a face with edges ``E = [x_1 - x_0, x_2 - x_0]`` (rest positions) the gradient of the
    linear interpolant of f is ``E^T (E E^T)^{-1} [f_1 - f_0, f_2 - f_0]``, a tangent vector in
    ambient coordinates; ``(D_k f)_v`` is component k of the area-weighted mean over the faces
    at v. Frame-free, so it applies to any surface.

    Args:
        vertices: Rest positions ``(n, 3)``.
        faces: Triangles ``(m, 3)``.

    Returns:
        Three sparse ``(n, n)`` matrices.

    """
    e = vertices[faces[:, 1:]] - vertices[faces[:, :1]]              # (m, 2, 3)
    metric = e @ e.transpose(0, 2, 1)
    area = 0.5 * np.linalg.norm(np.cross(e[:, 0], e[:, 1]), axis=1)
    if np.any(area <= 0):
        bad = int(np.argmin(area))
        raise InputError(f"phase space: face {bad} {faces[bad].tolist()} has zero rest area")
    # gradient of the barycentric basis functions 1, 2 (basis 0 is minus their sum)
    basis = np.linalg.solve(metric, e).transpose(0, 2, 1)          # (m, 3 dirs, 2)
    weights = area / np.bincount(faces.ravel(), np.repeat(area, 3), len(vertices))[faces].T
    rows, cols = np.repeat(faces, 3, axis=1).ravel(), np.tile(faces, 3).ravel()
    out = []
    for k in range(3):
        g = np.column_stack([-basis[:, k].sum(axis=1), basis[:, k, 0], basis[:, k, 1]])
        vals = (weights.T[:, :, None] * g[:, None, :]).ravel()
        out.append(sp.csr_matrix((vals, (rows, cols)), shape=(len(vertices),) * 2))
    return tuple(out)


def hat_frames(vertices: np.ndarray, faces: np.ndarray, hats: sp.csr_matrix) -> np.ndarray:
    """Orthonormal tangent pairs ``(u_j, v_j)`` per hat, ``(n_c, 2, 3)``.

    The hat's normal is the hat-weighted sum of the area-weighted face normals at its
    vertices; ``u_j`` is the unit projection of the coordinate axis least aligned with it.
    Derivatives along ``u_j, v_j`` are independent, where the three ambient ones are not
    (``n . grad = 0``).
    """
    normals = hats.T @ area_weighted_normals(np.asarray(vertices, dtype=np.float64), faces)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    axis = np.eye(3)[np.argmin(np.abs(normals), axis=1)]
    u = axis - np.einsum("jd,jd->j", axis, normals)[:, None] * normals
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.stack([u, np.cross(normals, u)], axis=1)


def hat_matrix(subdivisions: tuple[sp.spmatrix, ...], level: int) -> sp.csr_matrix:
    """Vertex hats of hierarchy level ``level`` on the shell: ``S_{L-1} ... S_level``."""
    if not 0 <= level < len(subdivisions):
        raise InputError(f"MultigridOptions.phase_level: must be in [0, {len(subdivisions)}), "
                         f"got {level}")
    hats = sp.csr_matrix(subdivisions[level])
    for s in subdivisions[level + 1:]:
        hats = (sp.csr_matrix(s) @ hats).tocsr()
    hats.eliminate_zeros()
    return hats


class UnionSum:
    """Weighted sums of sparse matrices of fixed patterns, on the union of their patterns.

    The positions of every part's entries (in its CSR order) in the union pattern, the
    diagonal included, are found once; a sum is then an array of the union's values, written
    part by part, instead of a scipy sum allocating each intermediate matrix.

    Args:
        parts: Named square CSR matrices (their patterns; values come with each sum).

    Attributes:
        pattern: The union pattern (sorted CSR, zero values, the full diagonal).
        diagonal: Positions of the diagonal entries in the union's values.
        has_penalty: Whether a part is named "penalty".

    """

    def __init__(self, parts: dict[str, sp.csr_matrix]) -> None:
        n = next(iter(parts.values())).shape[0]
        diagonal = np.arange(n, dtype=np.int64) * (n + 1)
        positions, indptr, cols = union_pattern(
            [*(entry_keys(m) for m in parts.values()), diagonal], (n, n))
        self._positions = dict(zip(parts, positions[:-1], strict=True))
        self.diagonal = positions[-1]
        self.pattern = sp.csr_matrix((np.zeros(cols.size), cols.astype(PETSc.IntType),
                                      indptr.astype(PETSc.IntType)), shape=(n, n))
        self.has_penalty = "penalty" in parts

    def add(self, values: np.ndarray, name: str, part: sp.csr_matrix, scale: float = 1.0
            ) -> None:
        """``values += scale part`` on the union pattern (``part`` in the pattern it had)."""
        values[self._positions[name]] += scale * part.data

    def matrix(self, values: np.ndarray) -> sp.csr_matrix:
        """Return the union pattern with ``values`` (sharing the pattern's arrays)."""
        out = sp.csr_matrix(self.pattern.shape)
        out.data, out.indices, out.indptr = values, self.pattern.indices, self.pattern.indptr
        return out


def union_pattern(keys: list[np.ndarray], shape: tuple[int, int]
                  ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Return the sorted union of entry keys (:func:`entry_keys`) as a CSR pattern of ``shape``.

    Returns:
        ``(positions, indptr, columns)``: every key array's positions in the union's values,
        and the union's row pointer and columns.

    """
    union = np.unique(np.concatenate(keys))
    rows, cols = np.divmod(union, shape[1])
    return ([np.searchsorted(union, k) for k in keys],
            np.searchsorted(rows, np.arange(shape[0] + 1)), cols)


class CoarseSpace:
    """Z's entries and fields and the factorised ``A_Z = Z^T (A + tau I + G^T G) Z``.

    Shared by the serial :class:`PhaseSpace` and the distributed
    :class:`solvers.decomposition.split_phase.SplitPhaseSpace`; a subclass builds ``self.z``
    (PETSc AIJ, serial or distributed) from the entries, sets its values in ``set_fields``,
    gives the rows of Z it holds (:meth:`_z_held`: a rank's own and halo vertices) and owns
    (:meth:`_z_rows`) and sums a product of its rows over the ranks (:meth:`_ranks_sum`).

    Args:
        vertices: Rest positions of the shell ``(n, 3)``.
        faces: Shell triangles.
        hats: Vertex hats ``(n, n_c)`` (:func:`hat_matrix`).
        threads: Threads of the block products.

    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, hats: sp.csr_matrix,
                 threads: int = 1) -> None:
        self.threads = threads
        self.gradients = surface_gradients(vertices, faces)
        self.rest = np.asarray(vertices, dtype=np.float64)
        self.frames = hat_frames(vertices, faces, hats)                # (n_c, 2, 3)
        coo = hats.tocoo()
        # entry e of Z: dof 3 v + c, column TEST_FIELDS j + m, value hat(v, j) t_m[v, c]
        index: Any = np.int32 if max(hats.shape) < np.iinfo(np.int32).max // 4 else np.int64
        self.vertex = np.repeat(coo.row.astype(index), 3 * TEST_FIELDS)
        self.hat = np.repeat(coo.col.astype(index), 3 * TEST_FIELDS)
        self.component = np.tile(np.repeat(np.arange(3, dtype=np.int8), TEST_FIELDS), coo.nnz)
        self.field = np.tile(np.arange(TEST_FIELDS, dtype=np.int8), 3 * coo.nnz)
        self.hat_value = np.repeat(coo.data, 3 * TEST_FIELDS)
        self.column = (TEST_FIELDS * self.hat + self.field).astype(index)
        self.n_columns = TEST_FIELDS * hats.shape[1]
        self.values = np.zeros(self.vertex.size, dtype=PETSc.ScalarType)
        self.counted = self.values.size
        """Leading entries of :attr:`values` counted in the column norms (a rank's own rows)."""
        self.z: Any = None
        self._base: tuple[np.ndarray, float] | None = None  # A_Z values before the fix, tau
        self._solver: SparseDirectSolver | None = None
        self._gram: tuple[TransposeBlockProduct | None, sp.csr_matrix | None] = (None, None)
        self._penalty: tuple[Any, Any, Any] | None = None  # (G, G Z, (G Z)^T (G Z))
        self._block_product: BlockPhaseProduct | None = None
        self._sum: UnionSum | None = None

    def _reorder(self, order: np.ndarray, counted: int | None = None) -> None:
        """Permute or select the entries (Z's CSR order; a rank's own and halo rows).

        ``counted``: the leading entries whose squares make the column norms (the rows this
        rank owns; None: all).
        """
        for name in ("vertex", "hat", "component", "field", "hat_value", "column"):
            setattr(self, name, getattr(self, name)[order])
        self.values = np.zeros(order.size, dtype=PETSc.ScalarType)
        self.counted = order.size if counted is None else counted

    def _field_values(self, x: np.ndarray, target: np.ndarray) -> None:
        """Every entry's value from x and the target y (``(n, 3)``), columns normalised.

        A new Z: the last full update and ``Z^T Z`` are out of date.
        """
        d = np.asarray(x, dtype=np.float64).reshape(-1, 3) - target
        grads = np.stack([g @ d for g in self.gradients], axis=-1)      # (n, 3 comp, 3 dir)
        z_values(self.values, self.hat_value, self.vertex, self.component, self.field,
                 self.hat, self.frames, d, grads)
        norms = self._column_sums(column_squares(self.values, self.column, self.counted,
                                                 self.n_columns))
        scale = np.where(norms > 0, 1.0 / np.sqrt(np.where(norms > 0, norms, 1.0)), 0.0)
        scale_columns(self.values, self.column, scale)
        self._base, self._gram = None, (self._gram[0], None)

    def set_fields(self, x: np.ndarray, target: np.ndarray) -> None:
        """Z's values from the positions x and the penalty target y (both ``(n, 3)``)."""
        raise NotImplementedError  # each subclass writes its own Z

    def refresh(self, fine: sp.csr_matrix, g: Any, tau: float,
                state: tuple[np.ndarray, np.ndarray] | None, shift_only: bool) -> FactorReport:
        """:meth:`update`, after new test fields from ``state`` unless ``shift_only``.

        ``state``: the ``(x, y)`` the fields are built from (:func:`field_state`; None: the
        rest positions). ``shift_only``: the matrix and fields of the last update, another
        shift (see :meth:`update`).
        """
        if not shift_only:
            x, y = state if state is not None else (self.rest,) * 2
            self.set_fields(x, y)
        return self.update(fine, g, tau, shift_only=shift_only)

    def update(self, fine: sp.csr_matrix, g: Any, tau: float = 0.0,
               shift_only: bool = False) -> FactorReport:
        """Factorise ``Z^T (A + tau I + G^T G) Z``.

        Args:
            fine: The rows of the Newton matrix A held here, without the shift: serially all
                of A, on a rank its own vertices' rows over its own and halo vertices'
                columns (scipy CSR of full 3 x 3 blocks, the same pattern at every call).
            g: The penalty factor G (scipy, or the distributed PETSc factor).
            tau: The diagonal shift, added as ``tau Z^T Z``.
            shift_only: ``fine`` is the matrix of the last full update (same fields), only
                the shift differs: ``Z^T A Z + (tau - tau_last) Z^T Z`` is factorised
                without the fine product (the shell Newton's retries with larger shifts).

        Returns:
            The LDL^T report: ``usable_spd`` False (negative pivots: an indefinite Newton
            matrix) means the caller must not use the correction.

        """
        if shift_only and self._base is not None and self._sum is not None:
            base, base_tau = self._base
            values = base.copy()
            self._sum.add(values, "gram", self._gram_matrix(), tau - base_tau)
        else:
            galerkin = self._galerkin_matrix(fine)
            penalty = None if g is None else self._penalty_part(g)
            if self._sum is None or self._sum.has_penalty != (penalty is not None):
                parts = {"galerkin": galerkin, "gram": self._gram_matrix()}
                self._sum = UnionSum(parts if penalty is None else {**parts, "penalty": penalty})
                self._solver = None
            values = np.zeros(self._sum.pattern.nnz)
            self._sum.add(values, "galerkin", galerkin)
            if tau:
                self._sum.add(values, "gram", self._gram_matrix(), tau)
            if penalty is not None:
                self._sum.add(values, "penalty", penalty)
            self._base = (values.copy(), tau)
        diagonal = values[self._sum.diagonal]  # a zero column (no wrinkles under a hat): 1
        values[self._sum.diagonal] = np.where(diagonal > 0, diagonal, diagonal + 1.0)
        if self._solver is None:  # a new pattern: its cheaper ordering, found once
            self._solver, report = cheapest_ordering(self._sum.matrix(values),
                                                     LinearSolverOptions(symmetric="ldlt"))
            return report
        return self._solver.factorize(self._sum.matrix(values))

    def _column_sums(self, sums: np.ndarray) -> np.ndarray:
        """Column sums of the entries held here, over all of Z (serial: all are here)."""
        return sums

    def _galerkin_matrix(self, fine: sp.csr_matrix) -> sp.csr_matrix:
        """``Z^T A Z`` over 3 x 3 blocks, every rank's ``Z_r^T (A Z)_r`` summed over the ranks.

        :class:`solvers.block_phase.BlockPhaseProduct` of the rows held here (patterns fixed
        at the first product), then :meth:`_ranks_sum`.
        """
        if self._block_product is None:
            self._block_product = BlockPhaseProduct(fine, self._z_held(), self.threads)
        return self._ranks_sum("galerkin", self._block_product.product(fine.data, self.values))

    def _z_held(self) -> sp.csr_matrix:
        """Return every row of Z held here, a scipy view of :attr:`values` (subclass)."""
        raise NotImplementedError

    def _z_rows(self) -> sp.csr_matrix:
        """Return the rows of Z this rank owns, a view of :attr:`values`' leading entries."""
        raise NotImplementedError

    def _ranks_sum(self, key: str, part: sp.csr_matrix) -> sp.csr_matrix:
        """Return the sum over the ranks of every rank's ``part`` (``key``: which product).

        Serial: ``part`` itself (every row of Z is here).
        """
        return part

    def _gram_matrix(self) -> sp.csr_matrix:
        """``Z^T Z`` of the current fields over 3 x 3 blocks, summed over the ranks.

        Computed at the first shifted update after new fields (pattern fixed at the first:
        :class:`solvers.block_phase.TransposeBlockProduct` of the own rows).
        """
        product, csr = self._gram
        if csr is None:
            own = self.values[:self.counted]
            if product is None:
                z = self._z_rows()
                product = TransposeBlockProduct(z, z)
            csr = self._ranks_sum("gram", product.product(own, own))
            self._gram = (product, csr)
        return csr

    def _penalty_part(self, g: Any) -> sp.csr_matrix:
        """``(G Z)^T (G Z)`` of the PETSc factor G, both products' symbolic parts reused."""
        if self._penalty is None or g is not self._penalty[0]:
            gz = g.matMult(self.z)
            self._penalty = (g, gz, gz.transposeMatMult(gz))
        else:
            _, gz, gtg = self._penalty
            g.matMult(self.z, result=gz)
            gz.transposeMatMult(gz, result=gtg)
        return scipy_csr(self._penalty[2])


class PhaseSpace(CoarseSpace):
    """The coarse space Z, its Galerkin matrix and the correction ``Q r = Z A_Z^{-1} Z^T r``.

    ``Z^T A Z`` is formed over 3 x 3 vertex blocks (:class:`solvers.block_phase.
    BlockPhaseProduct`, patterns from the first update).

    Args:
        vertices: Rest positions of the shell ``(n, 3)``.
        faces: Shell triangles.
        hats: Vertex hats ``(n, n_c)`` (:func:`hat_matrix`).
        threads: Threads of the ``Z^T A Z`` product.

    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, hats: sp.csr_matrix,
                 threads: int = 1) -> None:
        super().__init__(vertices, faces, hats, threads)
        rows = 3 * self.vertex + self.component
        order = np.lexsort((self.column, rows))
        self._reorder(order)
        indptr = np.searchsorted(rows[order], np.arange(3 * hats.shape[0] + 1))
        # PETSc wraps these arrays (no copy): they live as long as the matrix
        self.csr = (indptr.astype(PETSc.IntType), self.column.astype(PETSc.IntType), self.values)
        z: Any = PETSc.Mat()
        z.createAIJWithArrays((3 * hats.shape[0], self.n_columns), self.csr,
                              comm=PETSc.COMM_SELF)
        z.assemble()
        self.z = z
        self._g: tuple[sp.csr_matrix, Any] | None = None  # (scipy G, its PETSc copy)
        self._coarse_rhs = z.createVecs()[0]
        self._solution = self._coarse_rhs.duplicate()

    def set_fields(self, x: np.ndarray, target: np.ndarray) -> None:
        """Z's values from the positions x and the penalty target y (both ``(n, 3)``)."""
        self._field_values(x, target)
        self.z.stateIncrease()

    def _z_held(self) -> sp.csr_matrix:
        """Return Z as a scipy view of the arrays PETSc reads."""
        indptr, columns, values = self.csr
        return sp.csr_matrix((values, columns, indptr), shape=self.z.getSize(), copy=False)

    def _z_rows(self) -> sp.csr_matrix:
        """Return Z (every row is owned here)."""
        return self._z_held()

    def _penalty_part(self, g: Any) -> sp.csr_matrix:
        """``(G Z)^T (G Z)`` of the scipy G (copied to PETSc once per new object)."""
        if self._g is None or g is not self._g[0]:
            self._g = (g, petsc_aij(g))
        return super()._penalty_part(self._g[1])

    def correct(self, r: Any, out: Any) -> None:
        """``out = Z A_Z^{-1} Z^T r``."""
        assert self._solver is not None  # update() ran first (internal invariant)
        self.z.multTranspose(r, self._coarse_rhs)
        self._solution.setArray(self._solver.solve(self._coarse_rhs.getArray()))
        self.z.mult(self._solution, out)


@numba.njit(cache=True)
def z_values(out: np.ndarray, hat_value: np.ndarray, vertex: np.ndarray, component: np.ndarray,
              field: np.ndarray, hat: np.ndarray, frames: np.ndarray, d: np.ndarray,
              grads: np.ndarray) -> None:  # pragma: no cover (compiled)
    """Z's values: ``hat * d[v, c]`` (field 0) or ``hat * frame_{j, m-1} . grad d[v, c]``."""
    for e in range(out.size):
        v, c, m = vertex[e], component[e], field[e]
        if m == 0:
            value = d[v, c]
        else:
            t = frames[hat[e], m - 1]
            value = t[0] * grads[v, c, 0] + t[1] * grads[v, c, 1] + t[2] * grads[v, c, 2]
        out[e] = hat_value[e] * value


@numba.njit(cache=True)
def column_squares(values: np.ndarray, column: np.ndarray, counted: int,
                   n_columns: int) -> np.ndarray:  # pragma: no cover (compiled)
    """Sum of ``values[e]**2`` per column over the first ``counted`` entries (no temporaries)."""
    out = np.zeros(n_columns)
    for e in range(counted):
        out[column[e]] += values[e] * values[e]
    return out


@numba.njit(cache=True)
def scale_columns(values: np.ndarray, column: np.ndarray,
                  scale: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``values[e] *= scale[column[e]]`` in place."""
    for e in range(values.size):
        values[e] *= scale[column[e]]


def petsc_aij(csr: sp.csr_matrix, block: int = 1) -> Any:
    """Copy a scipy CSR matrix into a PETSc sequential AIJ (``block``: its block size)."""
    c = sp.csr_matrix(csr)
    c.sort_indices()
    return PETSc.Mat().createAIJ(
        c.shape, bsize=block,
        csr=(c.indptr.astype(PETSc.IntType), c.indices.astype(PETSc.IntType),
             c.data.astype(PETSc.ScalarType)), comm=PETSc.COMM_SELF)


def scipy_csr(mat: Any) -> sp.csr_matrix:
    """Copy a PETSc AIJ matrix into scipy CSR."""
    indptr, indices, data = mat.getValuesCSR()
    return sp.csr_matrix((data, indices, indptr), shape=mat.getSize())


class DeflatedPreconditioner:
    """``PCPython`` context of the deflation preconditioner A-DEF2, ``M + Q (I - A M)``.

    With the start ``x_0 = Q b`` (:meth:`start`) every CG residual satisfies ``Z^T r = 0``,
    where A-DEF2 equals the balancing preconditioner ``Q + (I - QA) M (I - AQ)`` (Tang et
    al. 2009, sec. 3.1) at one product with A and one coarse solve per iteration instead of
    two of each.

    Args:
        operator: The Newton matrix A (PETSc Mat, penalty included).
        multigrid: The set-up multigrid PC (M).
        phase: The :class:`PhaseSpace` (Q).

    """

    def __init__(self, operator: Any, multigrid: Any, phase: PhaseSpace) -> None:
        self.operator, self.multigrid, self.phase = operator, multigrid, phase
        self.residual, self.product = (operator.createVecs()[0] for _ in range(2))

    def start(self, b: Any, x: Any) -> None:
        """``x = Q b``: the initial guess that makes ``Z^T r_0 = 0``."""
        self.phase.correct(b, x)

    def apply(self, pc: Any, r: Any, y: Any) -> None:  # noqa: ARG002 (petsc4py signature)
        """``y = M r + Q (r - A M r)``."""
        self.multigrid.apply(r, y)
        self.operator.mult(y, self.product)
        self.residual.waxpy(-1.0, self.product, r)
        self.phase.correct(self.residual, self.product)
        y.axpy(1.0, self.product)


def deflated_cg(comm: Any, operator: Any, multigrid: Any, phase: Any) -> Any:
    """CG (unpreconditioned norm, nonzero start ``x_0 = Q b``) with A-DEF2 around ``multigrid``.

    ``phase`` is any coarse space with ``correct(r, out)`` (:class:`PhaseSpace` or its
    distributed form); the caller starts each solve with
    ``ksp.getPC().getPythonContext().start(b, x)``.
    """
    ksp: Any = PETSc.KSP().create(comm)
    ksp.setType("cg")
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    ksp.setInitialGuessNonzero(True)
    ksp.setOperators(operator)
    pc: Any = ksp.getPC()
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(DeflatedPreconditioner(operator, multigrid, phase))
    ksp.setUp()
    return ksp


def field_state(rest: np.ndarray, x: np.ndarray,
                target: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` as ``(n, 3)`` arrays: the state the test fields are built from.

    ``target`` None: the rest positions (the test fields are then the displacement's).
    """
    y = rest if target is None else np.asarray(target).reshape(-1, 3)
    return np.array(x, dtype=np.float64).reshape(-1, 3), y


def same_state(state: tuple[np.ndarray, np.ndarray],
               previous: tuple[np.ndarray, np.ndarray] | None) -> bool:
    """Whether ``state`` equals ``previous`` bitwise (then Z need not be rebuilt)."""
    return previous is not None and all(
        np.array_equal(a, b) for a, b in zip(state, previous, strict=True))
