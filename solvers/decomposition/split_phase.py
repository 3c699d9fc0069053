"""The wrinkle-phase coarse space over the split layout (:mod:`solvers.phase_space`, distributed).

The basis is the serial one: with ``d = x - y``, ``D_k`` the surface gradients and ``(u_j, v_j)``
the tangent frame of coarse hat ``phi_j``, the columns of Z are

    Z[3 v + c, 3 j + m] = phi_j(v) t_m[v, c] / ||column||,   t_0 = d, t_{1,2} = (u_j, v_j) . D d,

and the correction is ``Q r = Z A_Z^{-1} Z^T r`` with ``A_Z = Z^T (A + tau I + G^T G) Z``,
used by the deflation preconditioner A-DEF2 (Tang, Nabben, Vuik & Erlangga, J. Sci. Comput.
39, 2009) around the V-cycle. Distributed:

* Z is a ``MATMPIAIJ`` whose rows are the fine dofs of each rank (PETSc numbering of
  :class:`~.split_multigrid.LevelNumbering`) and whose columns are numbered by the owner of
  each hat (3 per hat); each rank computes the entries of its own rows (from the full x)
  into the arrays PETSc reads (:class:`~solvers.shared_aij.SharedAIJ`), the column norms
  summed over the ranks;
* ``A Z`` and ``(G Z)^T (G Z)`` are parallel products (symbolic parts reused), ``Z^T (A Z)``
  the sum of every rank's product of its own rows (3 x 3 blocks); ``A_Z``
  is small (3 columns per coarse hat) and is gathered to every rank and factorised there by
  the serial LDL^T, whose inertia says whether A is indefinite (as in the serial space);
* ``Q r``: ``Z^T r`` gathered to every rank, the small solve, ``Z`` times the owned part.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from models.backend import MPI, PETSc
from solvers.block_phase import TransposeBlockProduct
from solvers.phase_space import CoarseSpace
from solvers.shared_aij import SharedAIJ, range_start


def _gathered(mat: Any, comm: Any) -> sp.csr_matrix:
    """Every rank's rows of a distributed AIJ ``mat`` as one scipy CSR on every rank."""
    indptr, indices, data = mat.getValuesCSR()
    parts = comm.allgather((np.diff(indptr), indices, data))
    counts = np.concatenate([p[0] for p in parts])
    return sp.csr_matrix((np.concatenate([p[2] for p in parts]),
                          np.concatenate([p[1] for p in parts]),
                          np.concatenate([[0], np.cumsum(counts)])), shape=mat.getSize())


class FixedSum:
    """The sum over the ranks of every rank's matrix of a fixed pattern, on every rank.

    The union of the ranks' patterns and each rank's positions in it are found once
    (collective); each sum is one ``MPI_Allreduce`` of the union's values.

    Args:
        part: This rank's matrix (its pattern; the values come with each call).
        comm: Communicator.

    """

    def __init__(self, part: sp.csr_matrix, comm: Any) -> None:
        self.comm, self.shape = comm, part.shape
        coo = part.tocoo()  # the CSR order of part's values
        keys = coo.row.astype(np.int64) * part.shape[1] + coo.col
        union = np.unique(np.concatenate(comm.allgather(keys)))
        self._at = np.searchsorted(union, keys)
        rows, self._cols = np.divmod(union, part.shape[1])
        self._indptr = np.searchsorted(rows, np.arange(part.shape[0] + 1))
        self._size = union.size

    def __call__(self, values: np.ndarray) -> sp.csr_matrix:
        """Return the sum over the ranks of the matrices with these values (collective)."""
        total = np.zeros(self._size)
        total[self._at] = values
        self.comm.Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
        return sp.csr_matrix((total, self._cols, self._indptr), shape=self.shape)


def _rows_kept(m: sp.csr_matrix, rows: np.ndarray) -> sp.csr_matrix:
    """``m`` with every row outside ``rows`` emptied (the kept rows' entries in their order)."""
    keep = np.zeros(m.shape[0], dtype=bool)
    keep[rows] = True
    lengths = np.diff(m.indptr)
    entries = np.repeat(keep, lengths)
    indptr = np.concatenate([[0], np.cumsum(np.where(keep, lengths, 0))])
    return sp.csr_matrix((m.data[entries], m.indices[entries], indptr), shape=m.shape)


class SplitPhaseSpace(CoarseSpace):
    """Z over the ranks, the gathered ``A_Z`` and the correction ``Q r`` (module docstring).

    :meth:`CoarseSpace.update` factorises ``A_Z`` from the gathered products.

    Args:
        vertices: Rest positions of the shell ``(n, 3)`` (the same on every rank).
        faces: Shell triangles.
        hats: Vertex hats ``(n, n_c)`` (:func:`solvers.phase_space.hat_matrix`).
        fine: ``(dof, owned, sizes)`` of the fine level: (3n,) PETSc index of every dof,
            (3 n_r,) this rank's dofs in row order, (local, global) rows.
        columns: ``(dof, sizes)``: (3 n_c,) PETSc index of every column ``3 j + m`` and
            (local, global) columns.
        comm: Communicator.

    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, hats: sp.csr_matrix,
                 fine: tuple[np.ndarray, np.ndarray, tuple[int, int]],
                 columns: tuple[np.ndarray, tuple[int, int]], comm: Any) -> None:
        super().__init__(vertices, faces, hats)
        fine_dof, fine_owned, fine_sizes = fine
        hat_dof, hat_sizes = columns
        self.comm = comm
        owned = np.zeros(fine_dof.size, dtype=bool)
        owned[fine_owned] = True
        mine = np.flatnonzero(owned[3 * self.vertex + self.component])
        rows = fine_dof[3 * self.vertex[mine] + self.component[mine]]
        order = np.argsort(rows, kind="stable")
        self._reorder(mine[order])  # own rows only, by row
        self.gradients = tuple(_rows_kept(g, np.unique(self.vertex)) for g in self.gradients)
        start = range_start(comm, fine_sizes[0])
        indptr = np.searchsorted(rows[order] - start, np.arange(fine_sizes[0] + 1))
        self._own = (indptr, hat_dof[self.column].astype(PETSc.IntType), hat_sizes[1])
        self._az: Any = None
        self._transpose: TransposeBlockProduct | None = None
        self._sums: dict[str, FixedSum] = {}
        self._shared = SharedAIJ(comm, fine_sizes[0], fine_sizes[1], indptr, self._own[1],
                                 columns=hat_sizes)
        z = self.z = self._shared.mat
        self._rhs, self._solution = z.createVecRight(), z.createVecRight()
        self._scatter, self._full = PETSc.Scatter.toAll(self._rhs)
        self._range = self._rhs.getOwnershipRange()

    def set_fields(self, x: np.ndarray, target: np.ndarray) -> None:
        """Z's values from the positions x and the penalty target y (both ``(n, 3)``)."""
        self._field_values(x, target)
        self._shared.set_values(self.values)

    def _csr(self, mat: Any) -> sp.csr_matrix:
        """Gather a distributed product of Z to every rank as one scipy matrix."""
        return _gathered(mat, self.comm)

    def _z_rows(self) -> sp.csr_matrix:
        """Return the rank's rows of Z: a scipy view of the values PETSc reads, PETSc columns."""
        indptr, cols, n_cols = self._own
        return sp.csr_matrix((self.values, cols, indptr), shape=(indptr.size - 1, n_cols),
                             copy=False)

    def _galerkin_matrix(self, fine: Any) -> sp.csr_matrix:
        """``Z^T (A Z)``: ``A Z`` by PETSc (symbolic part reused), then ``Z_r^T (A Z)_r``.

        Every rank multiplies its own rows of Z and of ``A Z`` over 3 x 3 blocks
        (:class:`solvers.block_phase.TransposeBlockProduct`) and the parts are summed over the
        ranks on a pattern fixed at the first product (:meth:`_ranks_sum`): no PETSc transpose
        product, whose transposed Z and merged rows would stay allocated between iterations.
        """
        if self._az is None:
            self._az = fine.matMult(self.z)
        else:
            fine.matMult(self.z, result=self._az)
        indptr, cols, data = self._az.getValuesCSR()
        if self._transpose is None:
            az = sp.csr_matrix((data, cols, indptr), shape=(indptr.size - 1, self._own[2]))
            self._transpose = TransposeBlockProduct(self._z_rows(), az)
        return self._ranks_sum("galerkin", self._transpose.product(self.values, data))

    def _ranks_sum(self, key: str, part: sp.csr_matrix) -> sp.csr_matrix:
        """Sum every rank's ``part`` of the product ``key`` (collective; :class:`FixedSum`)."""
        if key not in self._sums:
            self._sums[key] = FixedSum(part, self.comm)
        return self._sums[key](part.data)

    def _column_sums(self, sums: np.ndarray) -> np.ndarray:
        """Add every rank's column sums (each rank holds the entries of its own rows)."""
        return np.asarray(self.comm.allreduce(sums))

    def correct(self, r: Any, out: Any) -> None:
        """``out = Z A_Z^{-1} Z^T r`` (collective)."""
        assert self._solver is not None  # update() ran first (internal invariant)
        self.z.multTranspose(r, self._rhs)
        self._scatter.scatter(self._rhs, self._full)  # insert, forward
        solution = self._solver.solve(self._full.getArray(readonly=True))
        self._solution.setArray(solution[self._range[0]: self._range[1]])
        self.z.mult(self._solution, out)


__all__ = ["SplitPhaseSpace"]
