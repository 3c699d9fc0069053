r"""The split shell's finest Galerkin product, ``P^T (A + tau I) P``, over 3 x 3 vertex blocks.

Rank r holds the rows of the Newton matrix at its vertices :math:`I_r` (columns at
:math:`I_r` and its halo), so the product is a sum of one term per rank,

.. math::  C = \sum_r S_{I_r}^T (A_{I_r} + \tau E_{I_r}) S, \qquad
           P = S \otimes I_3,

with :math:`S_{I_r}` the rows of the vertex subdivision matrix at :math:`I_r`, :math:`A_{I_r}`
the rank's rows and :math:`E_{I_r}` the identity's rows there. Each rank computes its term
with :class:`solvers.block_galerkin.BlockGalerkin` over its local vertices (the halo's rows
empty), the shift added as :math:`\tau S_{I_r}^T S_{I_r}` on the term's pattern, and sends
the rows of the coarse vertices another rank owns to that rank (one ``Alltoallv`` of values
in an order fixed at construction); the owner sums what arrives into a
:class:`solvers.shared_aij.SharedAIJ`. Nothing else is stored between products: PETSc's
``MatPtAP`` (``scalable``) keeps ``A P`` and the off-rank rows of P for its reuse, several
times the memory of this term's pattern (docs/notes/distributed-shell.md).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import MPI
from solvers.block_galerkin import BlockGalerkin
from solvers.shared_aij import SharedAIJ


class SplitGalerkin:
    """``C = P^T (A + tau I) P`` from this rank's Hessian rows, as a ``MATMPIAIJ`` (collective).

    Args:
        comm: Communicator (mpi4py).
        indptr: (3 m + 1,) row pointer of this rank's Hessian rows (its m vertices' dofs,
            vertex-major; full, column-sorted 3 x 3 blocks).
        indices: Their columns: dofs ``3 a + k`` of the local vertices (``a`` indexes
            ``local_vertices``, this rank's own m first).
        local_vertices: (L,) global ids of the local vertices, the m owned first.
        s: Vertex prolongation S (fine vertices x coarse vertices), the same on every rank.
        owner: (n_coarse,) rank owning every coarse vertex.
        dof: (3 n_coarse,) PETSc index of every coarse dof ``3 j + k``; rank r's rows are
            ``offsets[r] .. offsets[r + 1]``.
        offsets: (size + 1,) PETSc row ranges of the coarse level's ranks.
        threads: Threads of the local product.

    Attributes:
        mat: C (``MATMPIAIJ``, the coarse level's numbering); :meth:`update` refills it.

    """

    def __init__(self, comm: Any, indptr: np.ndarray, indices: np.ndarray,
                 local_vertices: np.ndarray, s: sp.spmatrix, owner: np.ndarray,
                 dof: np.ndarray, offsets: np.ndarray, threads: int = 1) -> None:
        self.comm = comm
        n_local, m3 = int(local_vertices.size), int(indptr.size) - 1
        if m3 % 3 or m3 > 3 * n_local:
            raise InputError(f"SplitGalerkin: {m3} Hessian rows for {n_local} local vertices")
        rows_ptr = np.concatenate([np.asarray(indptr, dtype=np.int64),
                                   np.full(3 * n_local - m3, int(indptr[-1]), dtype=np.int64)])
        pattern = sp.csr_matrix((np.ones(len(indices), dtype=np.int8), indices, rows_ptr),
                                shape=(3 * n_local, 3 * n_local))
        s_local = sp.csr_matrix(sp.csr_matrix(s)[np.asarray(local_vertices)])
        reached = np.unique(s_local.indices)  # the coarse vertices this rank's term touches
        s_local = sp.csr_matrix(s_local[:, reached])
        self._product = BlockGalerkin(pattern, s_local, threads)
        s_own = s_local[: m3 // 3]
        self._shift = self._product.image_positions(sp.csr_matrix(s_own.T @ s_own))
        self._exchange(reached, np.asarray(owner), np.asarray(dof), np.asarray(offsets))

    def _exchange(self, reached: np.ndarray, owner: np.ndarray, dof: np.ndarray,
                  offsets: np.ndarray) -> None:
        """Fix the send order of the term's entries and the owner-side sum (collective).

        Entries of rows this rank owns are summed in place; only the others travel.
        """
        comm, size, rank = self.comm, self.comm.size, self.comm.rank
        c = self._product.csr
        local_dof = (3 * reached[:, None] + np.arange(3)).reshape(-1)
        rows = np.repeat(np.arange(c.shape[0]), np.diff(c.indptr))
        total = int(offsets[-1])
        keys = dof[local_dof[rows]] * total + dof[local_dof[c.indices]]
        dest = owner[local_dof[rows] // 3]
        mine = dest == rank
        self._own = np.flatnonzero(mine).astype(np.int32)
        self._send = np.flatnonzero(~mine)[np.argsort(dest[~mine], kind="stable")].astype(
            np.int32)  # by destination rank
        counts = np.bincount(dest[~mine], minlength=size).astype(np.int64)
        recv_counts = np.empty(size, dtype=np.int64)
        comm.Alltoall(counts, recv_counts)
        # (counts, displacements) of the sends and the receives, fixed for every product
        self._sent = (counts, _displacements(counts))
        self._received = (recv_counts, _displacements(recv_counts))
        received = np.empty(int(recv_counts.sum()), dtype=np.int64)
        comm.Alltoallv([keys[self._send], self._sent, MPI.INT64_T],
                       [received, self._received, MPI.INT64_T])
        unique, slot = np.unique(np.concatenate([keys[self._own], received]),
                                 return_inverse=True)
        start, local = int(offsets[rank]), int(offsets[rank + 1] - offsets[rank])
        row_of = unique // total - start
        if unique.size and (row_of[0] < 0 or row_of[-1] >= local):
            raise InputError("SplitGalerkin: a coarse row arrived at a rank that does not "
                             "own it")
        indptr = np.zeros(local + 1, dtype=np.int64)
        np.cumsum(np.bincount(row_of, minlength=local), out=indptr[1:])
        self._matrix = SharedAIJ(comm, local, total, indptr, unique % total)
        if self._matrix.diagonal.size != local:
            raise InputError("SplitGalerkin: a coarse vertex's own rows lack the diagonal")
        # each entry's place in the matrix's own value arrays (diagonal block, then the other)
        place = self._matrix.entry_positions()[slot].astype(np.int32)
        self._place_own, self._place_received = place[: self._own.size], place[self._own.size:]
        self.mat = self._matrix.mat

    def update(self, values: np.ndarray, tau: float) -> Any:
        """Refill :attr:`mat` from the Hessian rows' ``values`` (the pattern's order) and ``tau``.

        Collective. Returns :attr:`mat`.
        """
        self._product.update(values)
        if tau:
            where, image = self._shift
            self._product.values[where] += tau * image
        received = np.empty(self._place_received.size)
        self.comm.Alltoallv([self._product.values[self._send], self._sent, MPI.DOUBLE],
                            [received, self._received, MPI.DOUBLE])
        _sum_into(*self._matrix.block_values, self._place_own, self._own,
                  self._product.values, self._place_received, received)
        self._matrix.values_changed()
        return self.mat


@numba.njit(cache=True)
def _sum_into(diagonal: np.ndarray, other: np.ndarray, place_own: np.ndarray, own: np.ndarray,
              values: np.ndarray, place_received: np.ndarray,
              received: np.ndarray) -> None:  # pragma: no cover (compiled)
    """Sum the own entries ``values[own]`` and the received ones into the two blocks.

    ``place``: position in the concatenation ``[diagonal, other]``. One fixed order (own
    entries, then the ranks' in rank order): the sum does not change between products.
    """
    diagonal[:] = 0.0
    other[:] = 0.0
    n = diagonal.size
    for k in range(own.size):
        p = place_own[k]
        if p < n:
            diagonal[p] += values[own[k]]
        else:
            other[p - n] += values[own[k]]
    for k in range(received.size):
        p = place_received[k]
        if p < n:
            diagonal[p] += received[k]
        else:
            other[p - n] += received[k]


def _displacements(counts: np.ndarray) -> np.ndarray:
    """Exclusive prefix sum of per-rank counts (MPI displacements)."""
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
