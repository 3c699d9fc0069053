r"""A distributed AIJ matrix whose values are numpy arrays filled by one fixed gather.

PETSc's ``MATMPIAIJ`` stores a rank's rows as two CSR blocks: the *diagonal* block (columns
this rank owns, local numbering) and the *off-diagonal* block (other columns, compacted).
``MatCreateMPIAIJWithSplitArrays`` wraps both blocks around arrays the caller keeps, without
copying them. :class:`SharedAIJ` builds those blocks once from a list of this rank's entries
``(row, column)`` in PETSc's global numbering, in the order in which their values arrive, and
keeps for every block entry the position of its value in that list. New values are then one
gather per block into PETSc's own storage:

.. math::  a_k = v_{\pi_A(k)}, \qquad b_k = v_{\pi_B(k)},

with no copy of the values on the PETSc side and none of the per-entry maps that
``MatSetPreallocationCOO`` keeps (two 8-byte integers per entry); where ``pi`` runs through
consecutive positions (a Hessian row's own columns) only the runs are kept (:class:`Gather`).
The pattern never changes, so every product and factorisation built on the matrix keeps its
symbolic part.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import PETSc


def range_start(comm: Any, local: int) -> int:
    """First global row of this rank (ranks own consecutive ranges in rank order)."""
    return int(comm.exscan(local) or 0) if comm.size > 1 else 0


def _index_type(n: int) -> type:
    """int32 for indices and positions below 2^31, else int64."""
    return np.int32 if n < np.iinfo(np.int32).max else np.int64


class SharedAIJ:
    """``MATMPIAIJ`` (``local`` of ``total`` rows on this rank) over numpy arrays.

    Collective. Ranks own consecutive row (and column) ranges in rank order; rank r's rows
    are given as CSR over global columns, its row ``i`` being the matrix row ``start_r + i``.
    Square by default (the columns split as the rows, the symmetric flag set); with
    ``columns = (local_cols, total_cols)`` rectangular (no flag, no diagonal).

    Args:
        comm: Communicator.
        local: Rows owned by this rank.
        total: Global rows.
        indptr: (local + 1,) CSR row pointer of this rank's entries.
        cols: Global column of each entry (any order within a row, no column twice).
        columns: ``(local, global)`` columns of a rectangular matrix (None: square).

    Attributes:
        mat: The PETSc matrix; its values are :meth:`set_values`'s.
        diagonal: Positions of the diagonal entries in the diagonal block's values (empty
            for a rectangular matrix).

    """

    def __init__(self, comm: Any, local: int, total: int, indptr: np.ndarray,
                 cols: np.ndarray, columns: tuple[int, int] | None = None) -> None:
        square = columns is None
        local_cols, total_cols = (local, total) if columns is None else columns
        start = range_start(comm, local_cols)
        index = _index_type(max(total, total_cols, len(cols)))
        indptr = np.asarray(indptr).astype(index)
        if indptr.shape != (local + 1,):
            raise InputError(f"SharedAIJ: indptr must have {local + 1} entries")
        cols = np.asarray(cols).astype(index)
        inside = (cols >= start) & (cols < start + local_cols)
        # sort every row's entries by a key that puts the diagonal block first
        key: np.ndarray = np.where(inside, cols - start, local_cols + cols).astype(index)
        order = sp.csr_matrix((np.arange(cols.size, dtype=np.float64), key, indptr),
                              shape=(local, local_cols + total_cols))
        order.sort_indices()
        if not order.has_canonical_format:  # sorted rows with a column twice
            raise InputError("SharedAIJ: an entry (row, column) is given twice")
        rows: np.ndarray = np.repeat(np.arange(local, dtype=index), np.diff(indptr))
        first = order.indices < local_cols
        self._take = [Gather(order.data[first].astype(index)),
                      Gather(order.data[~first].astype(index))]
        blocks = []
        for mask, shift in ((first, 0), (~first, local_cols)):
            block_ptr = np.zeros(local + 1, dtype=PETSc.IntType)
            np.cumsum(np.bincount(rows[mask], minlength=local), out=block_ptr[1:])
            blocks.append((block_ptr, (order.indices[mask] - shift).astype(PETSc.IntType),
                           np.zeros(int(mask.sum()), dtype=PETSc.ScalarType)))
        self._blocks = blocks  # PETSc reads these arrays: they live as long as the matrix
        self.diagonal = (np.flatnonzero(rows[first] == blocks[0][1]) if square
                         else np.zeros(0, dtype=np.int64))
        mat: Any = PETSc.Mat()
        self.mat = mat.createAIJWithArrays(((local, total), (local_cols, total_cols)),
                                           (blocks[0], blocks[1]), comm=comm)
        self.mat.assemble()
        if square:
            self.mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)

    @property
    def nnz(self) -> int:
        """Entries on this rank (the length of :meth:`set_values`' input)."""
        return self._take[0].size + self._take[1].size

    def entry_positions(self) -> np.ndarray:
        """Position of every entry (the constructor's order) in :attr:`block_values`' concatenation.

        For callers that add values into the blocks themselves (then :meth:`values_changed`).
        """
        positions = np.empty(self.nnz, dtype=np.int64)
        offset = 0
        for gather in self._take:
            positions[gather.expanded()] = offset + np.arange(gather.size)
            offset += gather.size
        return positions

    @property
    def block_values(self) -> tuple[np.ndarray, np.ndarray]:
        """The diagonal and off-diagonal blocks' value arrays, which PETSc reads in place."""
        return self._blocks[0][2], self._blocks[1][2]

    def values_changed(self) -> None:
        """Tell PETSc that :attr:`block_values` were written (its object state is bumped)."""
        self.mat.stateIncrease()

    def set_values(self, values: np.ndarray, shift: float = 0.0) -> None:
        """Take the entries' values (in the constructor's order), plus ``shift`` on the diagonal.

        Not collective: the values are written in place and PETSc's object state is bumped,
        so that preconditioners and products built on the matrix see them.
        """
        if values.shape != (self.nnz,):
            raise InputError(f"SharedAIJ.set_values: expected {self.nnz} values, "
                             f"got shape {values.shape}")
        for (_, _, data), gather in zip(self._blocks, self._take, strict=True):
            gather(values, data)
        if shift:
            self._blocks[0][2][self.diagonal] += shift
        self.mat.stateIncrease()


_CHUNK = 1 << 18
"""Entries gathered per ``np.take`` call."""


class Gather:
    """``out = values[take]`` for a fixed ``take``, kept as runs of consecutive positions.

    A rank's Hessian rows arrive with each row's own columns first and in order, so the
    diagonal block of a :class:`SharedAIJ` is one run per row; a block-upper copy takes
    runs of 3 (a vertex's three columns). When runs pay (at most half as many as entries)
    the run starts are kept, ``(out_start, in_start)`` per run (8 bytes per run in int32,
    against 4 per entry); otherwise the positions themselves.

    Args:
        take: (m,) positions in the input of every output entry.

    """

    def __init__(self, take: np.ndarray) -> None:
        take = np.asarray(take)
        self.size = int(take.size)
        index = _index_type(int(take.max(initial=0)) + 1)
        breaks = np.flatnonzero(np.diff(take) != 1) + 1
        if 2 * (breaks.size + 1) <= take.size:
            self.out_starts: np.ndarray | None = np.concatenate(
                [[0], breaks, [take.size]]).astype(_index_type(take.size + 1))
            self.in_starts = take[self.out_starts[:-1]].astype(index)
            self.take: np.ndarray | None = None
        else:
            self.out_starts, self.in_starts = None, np.zeros(0, dtype=index)
            self.take = take.astype(index)

    def expanded(self) -> np.ndarray:
        """Return the positions ``take`` themselves, (m,)."""
        if self.take is not None:
            return self.take
        assert self.out_starts is not None  # one of the two forms (internal invariant)
        lengths = np.diff(self.out_starts).astype(np.int64)
        return (np.repeat(self.in_starts.astype(np.int64) - self.out_starts[:-1], lengths)
                + np.arange(self.size))

    def __call__(self, values: np.ndarray, out: np.ndarray) -> None:
        """``out[:] = values[take]``."""
        if self.take is None:
            assert self.out_starts is not None  # one of the two forms (internal invariant)
            _gather_runs(self.out_starts, self.in_starts, values, out)
            return
        for lo in range(0, self.size, _CHUNK):
            np.take(values, self.take[lo: lo + _CHUNK], out=out[lo: lo + _CHUNK])


@numba.njit(cache=True)
def _gather_runs(out_starts: np.ndarray, in_starts: np.ndarray, values: np.ndarray,
                 out: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``out[o_r : o_{r+1}] = values[i_r : i_r + o_{r+1} - o_r]`` for every run r."""
    for r in range(in_starts.size):
        lo, hi, start = np.int64(out_starts[r]), np.int64(out_starts[r + 1]), np.int64(in_starts[r])
        if hi - lo > 8:  # a slice copy (vectorised); short runs element by element
            out[lo:hi] = values[start:start + hi - lo]
        else:
            for k in range(hi - lo):
                out[lo + k] = values[start + k]


class BlockUpperCopy:
    """Upper block triangle (``MATMPISBAIJ``, 3 x 3 blocks) of a symmetric matrix's rows.

    The same rows as :class:`SharedAIJ` (rank r's rows from ``start_r``, CSR over global
    columns), which must consist of full 3 x 3 vertex blocks with every vertex's dofs
    consecutive. Only the blocks on or above the block diagonal are kept: a product reads
    about half the bytes of the full AIJ rows (8 bytes per kept entry and one index per
    block instead of 12 bytes per entry), which is what bounds it. Values are gathered
    from the rows' values into a buffer that lives for one call and inserted into the
    fixed pattern (``MatSetValuesBlocked``).

    Args:
        comm: Communicator.
        local: Rows owned by this rank (a multiple of 3).
        total: Global size.
        indptr: (local + 1,) CSR row pointer of this rank's entries.
        cols: Global column of each entry.

    Attributes:
        mat: The PETSc ``MATMPISBAIJ`` (block size 3).

    """

    def __init__(self, comm: Any, local: int, total: int, indptr: np.ndarray,
                 cols: np.ndarray) -> None:
        bs = 3
        start = range_start(comm, local)
        if local % bs or start % bs or total % bs:
            raise InputError("BlockUpperCopy: row ranges must hold whole 3 x 3 blocks")
        positions = sp.csr_matrix((np.arange(1.0, len(cols) + 1.0), np.asarray(cols),
                                   np.asarray(indptr)), shape=(local, total))
        bsr = positions.tobsr(blocksize=(bs, bs))
        bsr.sort_indices()
        block_row = np.repeat(np.arange(local // bs), np.diff(bsr.indptr))
        keep = bsr.indices >= block_row + start // bs
        blocks = bsr.data[keep]
        if np.any(blocks == 0):
            raise InputError("BlockUpperCopy: the rows must consist of full 3 x 3 blocks")
        self._take = Gather((blocks.reshape(-1) - 1).astype(_index_type(len(cols))))
        self._ptr = np.zeros(local // bs + 1, dtype=PETSc.IntType)
        np.cumsum(np.bincount(block_row[keep], minlength=local // bs), out=self._ptr[1:])
        self._ind = bsr.indices[keep].astype(PETSc.IntType)
        on_diagonal = np.repeat(self._ind == block_row[keep] + start // bs, bs * bs)
        self._diagonal = np.flatnonzero(on_diagonal & np.tile(np.eye(bs, dtype=bool).ravel(),
                                                              self._ind.size))
        mat: Any = PETSc.Mat()
        self.mat = mat.createSBAIJ(((local, total), (local, total)), bs,
                                   csr=(self._ptr, self._ind), comm=comm)

    def set_values(self, values: np.ndarray, shift: float = 0.0) -> None:
        """Take the rows' values (the constructor's entry order), ``shift`` on the diagonal.

        Collective (the matrix is assembled).
        """
        data = np.empty(self._take.size, dtype=PETSc.ScalarType)  # PETSc copies it in
        self._take(values, data)
        if shift:
            data[self._diagonal] += shift
        self.mat.setValuesBlockedCSR(self._ptr, self._ind, data)
        self.mat.assemble()


__all__ = ["BlockUpperCopy", "Gather", "SharedAIJ", "range_start"]
