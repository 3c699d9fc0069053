"""The wrinkle-phase coarse space over the split layout (:mod:`solvers.phase_space`, distributed).

The basis is the serial one: with ``d = x - y``, ``D_k`` the surface gradients and ``(u_j, v_j)``
the tangent frame of coarse hat ``phi_j``, the columns of Z are

    Z[3 v + c, 3 j + m] = phi_j(v) t_m[v, c] / ||column||,   t_0 = d, t_{1,2} = (u_j, v_j) . D d,

and the correction is ``Q r = Z A_Z^{-1} Z^T r`` with ``A_Z = Z^T (A + tau I + G^T G) Z``,
used by the deflation preconditioner A-DEF2 (Tang, Nabben, Vuik & Erlangga, J. Sci. Comput.
39, 2009) around the V-cycle. Distributed:

* Z is a ``MATMPIAIJ`` whose rows are the fine dofs of each rank (PETSc numbering of
  :class:`~.split_multigrid.LevelNumbering`) and whose columns are numbered by the owner of
  each hat (3 per hat); each rank computes the entries of its own and its halo vertices'
  rows (from the full x), the column norms summed over the own rows of all ranks, and
  gives its own rows to PETSc (:class:`~solvers.shared_aij.SharedAIJ`);
* ``Z^T A Z`` is the sum of every rank's ``Z_r^T (A_r Z)``: A_r, the rank's rows of the
  Newton matrix, reaches only its own and halo vertices, so both factors are local
  (:class:`~solvers.block_phase.BlockPhaseProduct` over 3 x 3 blocks), and the parts are
  summed on a fixed pattern by one ``MPI_Allreduce``; ``Z^T Z`` likewise; ``(G Z)^T (G Z)``
  is a parallel PETSc product (symbolic part reused). ``A_Z`` is small (3 columns per
  coarse hat) and is factorised on every rank by the serial LDL^T, whose inertia says
  whether A is indefinite (as in the serial space);
* ``Q r``: ``Z^T r`` gathered to every rank, the small solve, ``Z`` times the owned part.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from models.backend import MPI, PETSc
from solvers.block_phase import TransposeBlockProduct
from solvers.phase_space import CoarseSpace, entry_keys, union_pattern
from solvers.shared_aij import SharedAIJ


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
        positions, self._indptr, self._cols = union_pattern(comm.allgather(entry_keys(part)),
                                                            part.shape)
        self._at = positions[comm.rank]
        self._size = self._cols.size

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
        fine: ``(local, sizes)`` of the fine level: the vertices of this rank's Hessian
            columns in their local order, its own ones first in the order of its rows, and
            its (local, global) rows.
        columns: ``(dof, sizes)``: (3 n_c,) PETSc index of every column ``3 j + m`` and
            (local, global) columns.
        comm: Communicator.
        threads: Threads of the block products.

    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, hats: sp.csr_matrix,
                 fine: tuple[np.ndarray, tuple[int, int]],
                 columns: tuple[np.ndarray, tuple[int, int]], comm: Any,
                 threads: int = 1) -> None:
        super().__init__(vertices, faces, hats, threads)
        local, fine_sizes = fine
        hat_dof, hat_sizes = columns
        self.comm = comm
        position = np.full(np.asarray(vertices).shape[0], -1, dtype=np.int64)
        position[local] = np.arange(local.size)
        held = np.flatnonzero(position[self.vertex] >= 0)
        rows = 3 * position[self.vertex[held]] + self.component[held]
        order = np.argsort(rows, kind="stable")
        rows = rows[order]
        own_rows = fine_sizes[0]
        self._reorder(held[order], counted=int(np.searchsorted(rows, own_rows)))
        self.gradients = tuple(_rows_kept(g, np.unique(self.vertex)) for g in self.gradients)
        indptr = np.searchsorted(rows, np.arange(3 * local.size + 1))
        self._held = (indptr, hat_dof[self.column].astype(PETSc.IntType), hat_sizes[1])
        self._sums: dict[str, FixedSum] = {}
        self._shared = SharedAIJ(comm, own_rows, fine_sizes[1], indptr[:own_rows + 1],
                                 self._held[1][:self.counted], columns=hat_sizes)
        z = self.z = self._shared.mat
        self._rhs, self._solution = z.createVecRight(), z.createVecRight()
        self._scatter, self._full = PETSc.Scatter.toAll(self._rhs)
        self._range = self._rhs.getOwnershipRange()

    def set_fields(self, x: np.ndarray, target: np.ndarray) -> None:
        """Z's values from the positions x and the penalty target y (both ``(n, 3)``)."""
        self._field_values(x, target)
        self._shared.set_values(self.values[:self.counted])

    def _penalty_part(self, g: Any) -> sp.csr_matrix:
        """``(G Z)^T (G Z)``: every rank's rows of ``G Z`` times their transpose, summed.

        ``G Z`` by PETSc's distributed product (symbolic part reused; its rows are the
        rank's clusters, 3 x 3 blocks of clusters and hats), then ``(G Z)_r^T (G Z)_r`` over
        blocks on a fixed pattern (:class:`solvers.block_phase.TransposeBlockProduct`) and
        one ``MPI_Allreduce`` (:meth:`_ranks_sum`): no distributed transpose product and no
        gather of its rows.
        """
        if self._penalty is None or g is not self._penalty[0]:
            gz = g.matMult(self.z)
            indptr, indices, values = gz.getValuesCSR()
            rows = sp.csr_matrix((values, indices, indptr),
                                 shape=(indptr.size - 1, gz.getSize()[1]))
            self._penalty = (g, gz, TransposeBlockProduct(rows, rows))
        else:
            g.matMult(self.z, result=self._penalty[1])
            values = self._penalty[1].getValuesCSR()[2]
        return self._ranks_sum("penalty", self._penalty[2].product(values, values))

    def _z_held(self) -> sp.csr_matrix:
        """Return Z's rows of this rank's own and halo vertices (local rows, PETSc columns)."""
        indptr, cols, n_cols = self._held
        return sp.csr_matrix((self.values, cols, indptr), shape=(indptr.size - 1, n_cols),
                             copy=False)

    def _z_rows(self) -> sp.csr_matrix:
        """Return the rank's own rows of Z: a view of :attr:`values`' leading entries."""
        indptr, cols, n_cols = self._held
        rows = self._shared.mat.getLocalSize()[0]
        return sp.csr_matrix((self.values[:self.counted], cols[:self.counted],
                              indptr[:rows + 1]), shape=(rows, n_cols), copy=False)

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
