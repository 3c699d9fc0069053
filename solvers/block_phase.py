r"""The phase space's Galerkin matrix ``Z^T A Z`` over 3 x 3 vertex blocks.

Z (:mod:`solvers.phase_space`) has a full 3 x 3 block ``Z_{vj}`` (rows: the components c of
vertex v, columns: the test fields m of hat j) wherever vertex v lies in the support of hat j,
and the Newton matrix A full 3 x 3 blocks ``A_{vw}``. The product is formed in two block
passes,

.. math::  (AZ)_{vk} = \sum_w A_{vw} Z_{wk},  \qquad
           (Z^T A Z)_{jk} = \sum_v Z_{vj}^T (AZ)_{vk},

whose patterns (the block patterns of A times the hats', then the hats' transposed times
that) are computed once; the values are rewritten in place at every product. Each block row
of a pass is summed by one thread in a fixed order (the result does not depend on the thread
count); threads take ranges of block rows of equal size. PETSc's scalar products visit the
same entries one scalar at a time and keep their own intermediate (``MatMatMult``,
``MatTransposeMatMult``).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.shell.schedule import balanced_cuts
from solvers.block_galerkin import (
    BlockRows,
    block_pattern,
    close_row,
    full_blocks,
    in_ranges,
    open_row,
    row_buffer,
)


class TransposeBlockProduct:
    """``C = Z^T B`` for fixed patterns of Z and B, both of full 3 x 3 blocks, on the same rows.

    Each coarse block row ``C_{j.} = sum_v Z_{vj}^T B_{v.}`` is summed by one thread (ranges
    of equal size), in a fixed order.

    Args:
        z_pattern: Pattern of Z (3 n x 3 n_c): scalar CSR, or its blocks (:class:`BlockRows`).
        b_pattern: Pattern of B (3 n x 3 m): scalar CSR, or its blocks.
        threads: Threads of each product.

    Attributes:
        pattern: Scalar CSR pattern of C (3 n_c x 3 m, full 3 x 3 blocks, zero values).

    """

    def __init__(self, z_pattern: sp.csr_matrix | BlockRows,
                 b_pattern: sp.csr_matrix | BlockRows, threads: int = 1) -> None:
        z = z_pattern if isinstance(z_pattern, BlockRows) else BlockRows.of(z_pattern)
        b = b_pattern if isinstance(b_pattern, BlockRows) else BlockRows.of(b_pattern)
        if z.shape[0] != b.shape[0]:
            raise InputError(f"TransposeBlockProduct: Z of shape {z.shape} and B of "
                             f"shape {b.shape} do not make Z^T B")
        zb_ptr, zb_idx = z.bptr, z.bcols
        bb_ptr, bb_idx = b.bptr, b.bcols
        n, n_c, m = zb_ptr.size - 1, z.shape[1] // 3, b.shape[1] // 3
        z_blocks = sp.csr_matrix((np.ones(zb_idx.size), zb_idx, zb_ptr), shape=(n, n_c))
        b_blocks = sp.csr_matrix((np.ones(bb_idx.size), bb_idx, bb_ptr), shape=(n, m))
        zt = sp.csr_matrix(z_blocks.T)
        zt.sort_indices()
        # position of each transposed entry (hat j, vertex v) within Z's block row v
        zt_pos = sp.csr_matrix((np.arange(zb_idx.size, dtype=np.float64) + 1, zb_idx, zb_ptr),
                               shape=(n, n_c)).T.tocsr()
        zt_pos.sort_indices()
        c = sp.csr_matrix(zt @ b_blocks)
        c.sort_indices()
        self._z_rows = z.indptr
        self._zt = (zt.indptr.astype(np.int64), zt.indices.astype(np.int64),
                    (zt_pos.data - 1).astype(np.int64) - zb_ptr[zt.indices])
        self._b = (b.indptr, bb_ptr, bb_idx)
        self._c = (c.indptr.astype(np.int64), c.indices.astype(np.int64))
        indptr, indices = full_blocks(*self._c)
        self.pattern = sp.csr_matrix((np.zeros(indices.size), indices, indptr),
                                     shape=(3 * n_c, 3 * m))
        self._c_rows = np.asarray(indptr, dtype=np.int64)
        self._cuts = balanced_cuts(self._c[0], threads)

    def product(self, z_values: np.ndarray, b_values: np.ndarray) -> sp.csr_matrix:
        """Return ``Z^T B`` (a new scipy CSR) from Z's and B's values in their CSR orders."""
        if z_values.size != self._z_rows[-1] or b_values.size != self._b[0][-1]:
            raise InputError(f"TransposeBlockProduct.product: expected {self._z_rows[-1]} "
                             f"values of Z and {self._b[0][-1]} of B, got {z_values.size} and "
                             f"{b_values.size}")
        values = np.zeros(self.pattern.nnz)
        in_ranges(_ztb_rows, _ztb_threads, self._cuts, self.pattern.shape[1] // 3, *self._zt,
                  self._z_rows, z_values, *self._b, b_values, *self._c, self._c_rows, values)
        return sp.csr_matrix((values, self.pattern.indices, self.pattern.indptr),
                             shape=self.pattern.shape)


class BlockPhaseProduct:
    """``Z_1^T A Z`` over 3 x 3 blocks for fixed patterns of A and Z (module docstring).

    A's rows are the leading rows of Z's (``Z_1``): serially all of them (``Z^T A Z``); on a
    rank of a split shell its own vertices' rows of the Newton matrix over its own and halo
    vertices' columns, so that the rank's share ``Z_r^T (A Z)_r`` needs no product with
    other ranks' rows (the shares are summed over the ranks by the caller).

    Args:
        a_pattern: Scalar CSR pattern of A (``3 m x 3 n``, full 3 x 3 blocks, ``m <= n``).
        z_pattern: Scalar CSR pattern of Z (``3 n x 3 n_c``, full 3 x 3 blocks).
        threads: Threads of each pass (numba ``prange`` over block-row ranges).

    Attributes:
        pattern: Scalar CSR pattern of ``Z_1^T A Z`` (full 3 x 3 blocks).

    """

    def __init__(self, a_pattern: sp.csr_matrix, z_pattern: sp.csr_matrix,
                 threads: int = 1) -> None:
        if a_pattern.shape[1] != z_pattern.shape[0] or a_pattern.shape[0] > a_pattern.shape[1]:
            raise InputError(f"BlockPhaseProduct: A of shape {a_pattern.shape} and Z of "
                             f"shape {z_pattern.shape} do not make Z_1^T A Z")
        ab_ptr, ab_idx = block_pattern(a_pattern)
        z = BlockRows.of(z_pattern)
        m, n, n_c = ab_ptr.size - 1, z.bptr.size - 1, z.shape[1] // 3
        a_blocks = sp.csr_matrix((np.ones(ab_idx.size), ab_idx, ab_ptr), shape=(m, n))
        z_blocks = sp.csr_matrix((np.ones(z.bcols.size), z.bcols, z.bptr), shape=(n, n_c))
        az = sp.csr_matrix(a_blocks @ z_blocks)
        az.sort_indices()
        az_rows = BlockRows.full(az.indptr, az.indices, n_c)  # no scalar columns needed
        self._a = (np.asarray(a_pattern.indptr, dtype=np.int64), ab_ptr, ab_idx)
        self._z = (z.indptr, z.bptr, z.bcols)
        self._lead = int(z.indptr[3 * m])  # Z_1's values: the leading ones of Z's
        z_lead = BlockRows(z.indptr[:3 * m + 1], z.bptr[:m + 1], z.bcols[:z.bptr[m]],
                           (3 * m, z.shape[1]))
        self._az = (az_rows.bptr, az_rows.bcols, az_rows.indptr,
                    np.zeros(9 * az_rows.bcols.size))
        self._transpose = TransposeBlockProduct(z_lead, az_rows, threads)
        self.pattern = self._transpose.pattern
        self._cuts = balanced_cuts(self._az[0], threads)

    def product(self, a_values: np.ndarray, z_values: np.ndarray) -> sp.csr_matrix:
        """Return ``Z_1^T A Z`` (a new scipy CSR) from A's and Z's values in their CSR orders."""
        if a_values.size != self._a[0][-1] or z_values.size != self._z[0][-1]:
            raise InputError(f"BlockPhaseProduct.product: expected {self._a[0][-1]} values of "
                             f"A and {self._z[0][-1]} of Z, got {a_values.size} and "
                             f"{z_values.size}")
        in_ranges(_az_rows, _az_threads, self._cuts, self.pattern.shape[0] // 3, *self._a,
                  a_values, *self._z, z_values, *self._az)
        return self._transpose.product(z_values[:self._lead], self._az[3])


@numba.njit(cache=True, nogil=True)
def _az_rows(lo: int, hi: int, n_cols: int, a_ptr: np.ndarray, ab_ptr: np.ndarray,
             ab_idx: np.ndarray, a_val: np.ndarray, z_ptr: np.ndarray, zb_ptr: np.ndarray,
             zb_idx: np.ndarray, z_val: np.ndarray, az_ptr: np.ndarray, az_idx: np.ndarray,
             az_rows: np.ndarray, az_val: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``(AZ)_{vk} = sum_w A_{vw} Z_{wk}`` for the block rows ``lo <= v < hi``.

    Every matrix is a scalar CSR of full 3 x 3 blocks: entry ``[r, c]`` of the k-th block of
    block row v sits at offset ``3 k + c`` of scalar row ``3 v + r``.
    """
    where = np.zeros(n_cols, dtype=np.int64)
    for v in range(lo, hi):
        for q in range(az_ptr[v], az_ptr[v + 1]):
            where[az_idx[q]] = 3 * (q - az_ptr[v])
        for r in range(3):
            for e in range(az_rows[3 * v + r], az_rows[3 * v + r + 1]):
                az_val[e] = 0.0
        o0, o1, o2 = az_rows[3 * v], az_rows[3 * v + 1], az_rows[3 * v + 2]
        r0, r1, r2 = a_ptr[3 * v], a_ptr[3 * v + 1], a_ptr[3 * v + 2]
        for k in range(ab_ptr[v + 1] - ab_ptr[v]):
            w, o = ab_idx[ab_ptr[v] + k], 3 * k
            a00, a01, a02 = a_val[r0 + o], a_val[r0 + o + 1], a_val[r0 + o + 2]
            a10, a11, a12 = a_val[r1 + o], a_val[r1 + o + 1], a_val[r1 + o + 2]
            a20, a21, a22 = a_val[r2 + o], a_val[r2 + o + 1], a_val[r2 + o + 2]
            s0, s1, s2 = z_ptr[3 * w], z_ptr[3 * w + 1], z_ptr[3 * w + 2]
            for h in range(zb_ptr[w + 1] - zb_ptr[w]):
                q, p = where[zb_idx[zb_ptr[w] + h]], 3 * h
                for m in range(3):
                    z0, z1, z2 = z_val[s0 + p + m], z_val[s1 + p + m], z_val[s2 + p + m]
                    az_val[o0 + q + m] += a00 * z0 + a01 * z1 + a02 * z2
                    az_val[o1 + q + m] += a10 * z0 + a11 * z1 + a12 * z2
                    az_val[o2 + q + m] += a20 * z0 + a21 * z1 + a22 * z2


@numba.njit(cache=True, parallel=True)
def _az_threads(cuts: np.ndarray, n_cols: int, a_ptr: np.ndarray, ab_ptr: np.ndarray,
                ab_idx: np.ndarray, a_val: np.ndarray, z_ptr: np.ndarray, zb_ptr: np.ndarray,
                zb_idx: np.ndarray, z_val: np.ndarray, az_ptr: np.ndarray, az_idx: np.ndarray,
                az_rows: np.ndarray, az_val: np.ndarray) -> None:  # pragma: no cover (compiled)
    """:func:`_az_rows` over the block-row ranges ``cuts``, one per thread."""
    for t in numba.prange(cuts.size - 1):
        _az_rows(cuts[t], cuts[t + 1], n_cols, a_ptr, ab_ptr, ab_idx, a_val, z_ptr, zb_ptr,
                 zb_idx, z_val, az_ptr, az_idx, az_rows, az_val)


@numba.njit(cache=True, nogil=True)
def _ztb_rows(lo: int, hi: int, n_cols: int, zt_ptr: np.ndarray, zt_idx: np.ndarray,
              zt_pos: np.ndarray, z_ptr: np.ndarray, z_val: np.ndarray, b_ptr: np.ndarray,
              bb_ptr: np.ndarray, bb_idx: np.ndarray, b_val: np.ndarray, c_ptr: np.ndarray,
              c_idx: np.ndarray, c_rows: np.ndarray,
              c_val: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``C_{jk} = sum_v Z_{vj}^T B_{vk}`` for the coarse block rows ``lo <= j < hi``.

    ``zt_pos``: the block position of ``Z_{vj}`` within Z's block row v. A coarse row's
    blocks are summed in a row buffer (``where``: block column -> slot), then written to C's
    three scalar rows.
    """
    where = np.zeros(n_cols, dtype=np.int64)
    buf = row_buffer(c_ptr, lo, hi)
    for j in range(lo, hi):
        width = open_row(j, c_ptr, c_idx, where, buf)
        for e in range(zt_ptr[j], zt_ptr[j + 1]):
            v, p = zt_idx[e], 3 * zt_pos[e]
            s0, s1, s2 = z_ptr[3 * v] + p, z_ptr[3 * v + 1] + p, z_ptr[3 * v + 2] + p
            t0, t1, t2 = b_ptr[3 * v], b_ptr[3 * v + 1], b_ptr[3 * v + 2]
            for k in range(bb_ptr[v + 1] - bb_ptr[v]):
                q, o = where[bb_idx[bb_ptr[v] + k]], 3 * k
                for m in range(3):
                    z0, z1, z2 = z_val[s0 + m], z_val[s1 + m], z_val[s2 + m]
                    for n in range(3):
                        buf[q, 3 * m + n] += (z0 * b_val[t0 + o + n] + z1 * b_val[t1 + o + n]
                                              + z2 * b_val[t2 + o + n])
        close_row(j, width, buf, c_rows, c_val)


@numba.njit(cache=True, parallel=True)
def _ztb_threads(cuts: np.ndarray, n_cols: int, zt_ptr: np.ndarray, zt_idx: np.ndarray,
                 zt_pos: np.ndarray, z_ptr: np.ndarray, z_val: np.ndarray, b_ptr: np.ndarray,
                 bb_ptr: np.ndarray, bb_idx: np.ndarray, b_val: np.ndarray, c_ptr: np.ndarray,
                 c_idx: np.ndarray, c_rows: np.ndarray,
                 c_val: np.ndarray) -> None:  # pragma: no cover (compiled)
    """:func:`_ztb_rows` over the coarse block-row ranges ``cuts``, one per thread."""
    for t in numba.prange(cuts.size - 1):
        _ztb_rows(cuts[t], cuts[t + 1], n_cols, zt_ptr, zt_idx, zt_pos, z_ptr, z_val, b_ptr, bb_ptr,
                  bb_idx, b_val, c_ptr, c_idx, c_rows, c_val)


__all__ = ["BlockPhaseProduct", "TransposeBlockProduct"]
