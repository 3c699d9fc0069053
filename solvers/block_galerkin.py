r"""Galerkin products of the subdivision hierarchy over 3 x 3 vertex blocks, ``P^T A P``.

The shell's prolongations act on each coordinate alike, ``P = S \otimes I_3`` with S the
vertex subdivision matrix (:func:`solvers.multigrid.vector_prolongation`), and the Newton
matrix is made of full 3 x 3 vertex blocks (:mod:`models.shell.assembly`). The coarse matrix
is then, block by block,

.. math::  C_{ij} = \sum_{a, b} S_{ai} \, S_{bj} \, A_{ab}  \qquad (3 \times 3 \text{ blocks}),

one scalar weight per block pair where a scalar ``MatPtAP`` visits nine index pairs, and no
stored intermediate ``A P``. C's pattern follows from the patterns of S and A (computed once);
every later product writes C's values in place, in the scalar CSR layout PETSc reads (a
``MATSEQAIJ`` over the arrays), so the next coarser product, the smoothers and the coarse
solve read C as any level matrix. Each coarse block row is summed by one thread in the order
of its fine rows and their blocks (the result does not depend on the thread count); threads
take ranges of coarse block rows of equal size.

The products from the finest level down form a :class:`GalerkinChain`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import PETSc
from models.shell.schedule import balanced_cuts


def full_blocks(bptr: np.ndarray, bcols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scalar CSR ``(indptr, indices)`` of full 3 x 3 blocks on a block pattern.

    Scalar row ``3 I + r`` holds the blocks of block row ``I`` in their order, block ``k`` of
    the row at offset ``3 k``: columns ``(3 J_k, 3 J_k + 1, 3 J_k + 2)``.
    """
    indptr = scalar_indptr(bptr)
    lengths = np.diff(indptr)
    segment = (3 * np.asarray(bcols, dtype=np.int64)[:, None] + np.arange(3)).reshape(-1)
    first = np.repeat(3 * np.asarray(bptr[:-1], dtype=np.int64), 3)
    ramp = np.arange(indptr[-1]) - np.repeat(indptr[:-1] - first, lengths)
    return indptr, segment[ramp]


def scalar_indptr(bptr: np.ndarray) -> np.ndarray:
    """Scalar row pointer (int64) of full 3 x 3 blocks on the block row pointer ``bptr``."""
    lengths = np.repeat(3 * np.diff(np.asarray(bptr, dtype=np.int64)), 3)
    indptr = np.zeros(lengths.size + 1, dtype=np.int64)
    np.cumsum(lengths, out=indptr[1:])
    return indptr


@dataclass(frozen=True, eq=False)
class BlockRows:
    """A scalar CSR pattern made of full 3 x 3 blocks, held by its blocks.

    Attributes:
        indptr: Scalar row pointer (int64).
        bptr: Block row pointer (int64).
        bcols: Block column of every block, in the rows' order (int64).
        shape: Scalar shape.

    """

    indptr: np.ndarray
    bptr: np.ndarray
    bcols: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def of(cls, pattern: sp.csr_matrix) -> BlockRows:
        """Read and check the blocks of a scalar CSR pattern (:func:`block_pattern`)."""
        bptr, bcols = block_pattern(pattern)
        return cls(np.asarray(pattern.indptr, dtype=np.int64), bptr, bcols, pattern.shape)

    @classmethod
    def full(cls, bptr: np.ndarray, bcols: np.ndarray, block_columns: int) -> BlockRows:
        """Full 3 x 3 blocks on a block pattern, without building the scalar columns."""
        indptr = scalar_indptr(bptr)
        return cls(indptr, np.asarray(bptr, dtype=np.int64), np.asarray(bcols, dtype=np.int64),
                   (indptr.size - 1, 3 * block_columns))


def block_pattern(pattern: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Block ``(indptr, indices)`` of a scalar CSR made of full 3 x 3 blocks.

    Raises:
        InputError: a row is not made of whole blocks, or the three rows of a vertex differ.

    """
    n = pattern.shape[0]
    lengths = np.diff(pattern.indptr)
    message = ("block product: the matrix's rows must hold full, column-sorted 3 x 3 blocks "
               "(3 dofs per vertex)")
    if n % 3 or pattern.shape[1] % 3 or np.any(lengths % 3) \
            or np.any(lengths[0::3] != lengths[1::3]) or np.any(lengths[0::3] != lengths[2::3]):
        raise InputError(message)
    per_row = lengths[0::3] // 3
    bptr = np.zeros(n // 3 + 1, dtype=np.int64)
    np.cumsum(per_row, out=bptr[1:])
    k = np.arange(bptr[-1]) - np.repeat(bptr[:-1], per_row)
    bcols = (np.asarray(pattern.indices[np.repeat(pattern.indptr[0:-1:3], per_row) + 3 * k])
             // 3).astype(np.int64)
    if not _is_full_blocks(np.asarray(pattern.indptr), np.asarray(pattern.indices), bptr,
                           bcols):
        raise InputError(message)
    return bptr, bcols


@numba.njit(cache=True)
def _is_full_blocks(indptr: np.ndarray, indices: np.ndarray, bptr: np.ndarray,
                    bcols: np.ndarray) -> bool:  # pragma: no cover (compiled)
    """Whether scalar row ``3 I + r`` holds exactly the columns ``3 J_k + (0, 1, 2)``.

    The blocks ``J_k`` of block row I in their order (:func:`full_blocks`' layout), checked
    entry by entry without building the scalar pattern.
    """
    for i in range(bptr.size - 1):
        for r in range(3):
            start = indptr[3 * i + r]
            if indptr[3 * i + r + 1] - start != 3 * (bptr[i + 1] - bptr[i]):
                return False
            for k in range(bptr[i], bptr[i + 1]):
                o = start + 3 * (k - bptr[i])
                for c in range(3):
                    if indices[o + c] != 3 * bcols[k] + c:
                        return False
    return True


def in_ranges(kernel: Any, threads_kernel: Any, cuts: np.ndarray, *args: Any) -> None:
    """Run ``kernel(lo, hi, *args)`` on the one range, or ``threads_kernel`` over the ranges.

    One range calls the plain compiled function: a numba parallel region would start its
    thread pool, whose waiting threads cost CPU time, for a single range.
    """
    if cuts.size == 2:
        kernel(0, int(cuts[-1]), *args)
    else:
        threads_kernel(cuts, *args)


class BlockGalerkin:
    """``C = P^T A P`` with ``P = S (x) I_3`` over 3 x 3 blocks (module docstring).

    Args:
        pattern: Scalar CSR pattern of the fine matrix A (full, column-sorted 3 x 3 blocks);
            its values are given to :meth:`update` in this CSR order.
        s: Vertex prolongation S (fine vertices x coarse vertices).
        threads: Threads of :meth:`update` (numba ``prange`` over coarse row ranges).

    Attributes:
        mat: C as a PETSc ``MATSEQAIJ`` (block size 3) over :attr:`values`; flagged symmetric,
            as the shell's Newton matrices are (A symmetric gives C symmetric).
        values: C's values in its scalar CSR order.
        csr: C as a scipy CSR over :attr:`values` and the index arrays PETSc reads (a view:
            it changes with every product); its pattern is the next coarser product's.

    """

    def __init__(self, pattern: sp.csr_matrix, s: sp.spmatrix, threads: int = 1) -> None:
        s_csr = sp.csr_matrix(s, dtype=np.float64)
        s_csr.sort_indices()
        if pattern.shape[0] != pattern.shape[1]:
            raise InputError(f"BlockGalerkin: the fine matrix must be square, got "
                             f"{pattern.shape}")
        if 3 * s_csr.shape[0] != pattern.shape[0]:
            raise InputError(f"BlockGalerkin: S has {s_csr.shape[0]} fine vertices, the "
                             f"matrix {pattern.shape[0] // 3}")
        bptr, bcols = block_pattern(pattern)
        blocks = sp.csr_matrix((np.ones(bcols.size), bcols, bptr), shape=(bptr.size - 1,) * 2)
        coarse = sp.csr_matrix(s_csr.T @ blocks @ s_csr)
        coarse.sort_indices()
        st = sp.csr_matrix(s_csr.T)
        st.sort_indices()
        self._a = (np.asarray(pattern.indptr, dtype=np.int64), bptr, bcols)
        self._s = (s_csr.indptr.astype(np.int64), s_csr.indices.astype(np.int64), s_csr.data)
        self._st = (st.indptr.astype(np.int64), st.indices.astype(np.int64), st.data)
        self._c_blocks = (coarse.indptr.astype(np.int64), coarse.indices.astype(np.int64))
        indptr, indices = full_blocks(*self._c_blocks)
        size = indptr.size - 1
        self.values = np.zeros(indices.size, dtype=PETSc.ScalarType)
        self._c_rows = indptr
        self._cuts = balanced_cuts(self._c_blocks[0], threads)
        # PETSc reads these arrays without a copy: they live as long as the matrix
        self._arrays = (indptr.astype(PETSc.IntType), indices.astype(PETSc.IntType), self.values)
        self.csr = sp.csr_matrix(self._arrays[::-1], shape=(size, size), copy=False)
        mat: Any = PETSc.Mat()
        self.mat = mat.createAIJWithArrays((size, size), self._arrays, bsize=3,
                                           comm=PETSc.COMM_SELF)
        self.mat.assemble()
        self.mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)

    def image_positions(self, image: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
        """Positions in :attr:`values` of ``image (x) I_3`` and its values there.

        ``image``: a vertex-level matrix on C's block pattern (found by block keys, a ninth
        of the scalar entries).
        """
        bptr, bcols = self._c_blocks
        nb = bptr.size - 1
        img = sp.csr_matrix(image)
        img.sort_indices()
        if img.shape != (nb, nb):
            raise InputError(f"BlockGalerkin.image_positions: a {img.shape} image for "
                             f"{nb} coarse vertices")
        keys = entry_keys(sp.csr_matrix((np.ones(bcols.size), bcols, bptr), shape=(nb, nb)))
        wanted = entry_keys(img)
        rows = wanted // nb
        block = np.minimum(np.searchsorted(keys, wanted), keys.size - 1)
        if np.any(keys[block] != wanted):
            raise InputError("BlockGalerkin.image_positions: an image entry outside the "
                             "level's block pattern")
        r = np.arange(3)
        where = self._c_rows[3 * rows[:, None] + r] + 3 * (block - bptr[rows])[:, None] + r
        return where.ravel(), np.repeat(np.asarray(img.data, dtype=np.float64), 3)

    def update(self, a_values: np.ndarray) -> None:
        """Compute C's values from A's (``a_values`` in the pattern's scalar CSR order)."""
        if a_values.ndim != 1 or a_values.size != self._a[0][-1]:
            raise InputError(f"BlockGalerkin.update: expected {self._a[0][-1]} values, got "
                             f"shape {a_values.shape}")
        args = (*self._a, a_values, *self._s, *self._st, *self._c_blocks, self._c_rows,
                self.values)
        in_ranges(_galerkin_rows, _galerkin_threads, self._cuts, *args)
        self.mat.stateIncrease()


class GalerkinChain:
    """The level matrices ``A_l = P_l^T A_{l+1} P_l`` from the finest down (:class:`BlockGalerkin`).

    Args:
        pattern: Scalar CSR pattern of the finest matrix (full 3 x 3 blocks).
        vertex_prolongations: ``S_l`` coarse to fine, the last one ending at the finest level.
        threads: Threads of each product.

    Attributes:
        products: One :class:`BlockGalerkin` per level below the finest, fine to coarse.

    """

    def __init__(self, pattern: sp.csr_matrix, vertex_prolongations: tuple[sp.spmatrix, ...],
                 threads: int = 1) -> None:
        self.products: list[BlockGalerkin] = []
        self._images: list[tuple[np.ndarray, np.ndarray]] = []
        for s in reversed(vertex_prolongations):
            self.products.append(BlockGalerkin(pattern, s, threads))
            pattern = self.products[-1].csr

    def update(self, fine_values: np.ndarray) -> list[Any]:
        """Recompute every level from the finest matrix's values; their matrices, coarse first."""
        values = fine_values
        for product in self.products:
            product.update(values)
            values = product.values
        return [product.mat for product in reversed(self.products)]

    def set_shift_images(self, images: list[sp.csr_matrix]) -> None:
        """Take the identity's Galerkin image on every level, fine to coarse, for :meth:`shift`.

        ``images[k]``: the vertex-level ``S^T .. S`` of product k (its scalar image is
        ``images[k] (x) I_3``; :func:`solvers.multigrid.shift_images` of the vertex
        prolongations), inside the product's block pattern; positions found once.
        """
        self._images = [product.image_positions(image)
                        for product, image in zip(self.products, images, strict=True)]

    def shift(self, step: float) -> list[Any]:
        """Add ``step`` times the identity's image to every level; the matrices, coarse first.

        The levels of ``A + (tau + step) I`` from those of ``A + tau I`` (the product is
        linear); needs :meth:`set_shift_images`.
        """
        if step:
            for product, (where, image) in zip(self.products, self._images, strict=True):
                product.values[where] += step * image
                product.mat.stateIncrease()
        return [product.mat for product in reversed(self.products)]


def entry_keys(m: sp.csr_matrix) -> np.ndarray:
    """``row * columns + column`` of every entry of a CSR matrix, in its storage order."""
    rows = np.repeat(np.arange(m.shape[0], dtype=np.int64), np.diff(m.indptr))
    return rows * m.shape[1] + m.indices


@numba.njit(cache=True, nogil=True)
def row_buffer(c_ptr: np.ndarray, lo: int, hi: int) -> np.ndarray:  # pragma: no cover
    """Return a buffer of 3 x 3 blocks as wide as the widest block row ``lo .. hi`` of C."""
    widest = 1
    for i in range(lo, hi):
        widest = max(widest, c_ptr[i + 1] - c_ptr[i])
    return np.zeros((widest, 9))


@numba.njit(cache=True, nogil=True)
def open_row(i: int, c_ptr: np.ndarray, c_idx: np.ndarray, where: np.ndarray,
             buf: np.ndarray) -> int:  # pragma: no cover (compiled)
    """Zero the buffer for C's block row i, ``where[column] = slot``; return the row's width."""
    width = c_ptr[i + 1] - c_ptr[i]
    for q in range(width):
        where[c_idx[c_ptr[i] + q]] = q
        for m in range(9):
            buf[q, m] = 0.0
    return width


@numba.njit(cache=True, nogil=True)
def close_row(i: int, width: int, buf: np.ndarray, c_rows: np.ndarray,
              c_val: np.ndarray) -> None:  # pragma: no cover (compiled)
    """Write the buffer of C's block row i (row-major blocks) into its three scalar rows."""
    for r in range(3):
        row = c_rows[3 * i + r]
        for q in range(width):
            for c in range(3):
                c_val[row + 3 * q + c] = buf[q, 3 * r + c]


@numba.njit(cache=True, parallel=True)
def _galerkin_threads(cuts: np.ndarray, a_ptr: np.ndarray, ab_ptr: np.ndarray,
                      ab_idx: np.ndarray, a_val: np.ndarray, s_ptr: np.ndarray,
                      s_idx: np.ndarray, s_val: np.ndarray, st_ptr: np.ndarray,
                      st_idx: np.ndarray, st_val: np.ndarray, c_ptr: np.ndarray,
                      c_idx: np.ndarray, c_scalar_ptr: np.ndarray,
                      c_val: np.ndarray) -> None:  # pragma: no cover (compiled)
    """:func:`_galerkin_rows` over the coarse block-row ranges ``cuts``, one per thread."""
    for t in numba.prange(cuts.size - 1):
        _galerkin_rows(cuts[t], cuts[t + 1], a_ptr, ab_ptr, ab_idx, a_val, s_ptr, s_idx, s_val,
                       st_ptr, st_idx, st_val, c_ptr, c_idx, c_scalar_ptr, c_val)


@numba.njit(cache=True, nogil=True)
def _galerkin_rows(lo: int, hi: int, a_ptr: np.ndarray, ab_ptr: np.ndarray, ab_idx: np.ndarray,
                   a_val: np.ndarray, s_ptr: np.ndarray, s_idx: np.ndarray, s_val: np.ndarray,
                   st_ptr: np.ndarray, st_idx: np.ndarray, st_val: np.ndarray,
                   c_ptr: np.ndarray, c_idx: np.ndarray, c_scalar_ptr: np.ndarray,
                   c_val: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``C_ij = sum_a S_ai sum_b S_bj A_ab`` for the coarse block rows ``lo <= i < hi``.

    Block ``k`` of fine block row ``a`` sits at offset ``3 k`` of A's scalar rows ``3 a + r``.
    A coarse row's blocks are summed in a row buffer of contiguous 3 x 3 blocks (``where``:
    block column -> buffer slot), then written to C's three scalar rows.
    """
    where = np.zeros(c_ptr.size - 1, dtype=np.int64)
    buf = row_buffer(c_ptr, lo, hi)
    for i in range(lo, hi):
        width = open_row(i, c_ptr, c_idx, where, buf)
        for e in range(st_ptr[i], st_ptr[i + 1]):
            a, w_a = st_idx[e], st_val[e]
            r0, r1, r2 = a_ptr[3 * a], a_ptr[3 * a + 1], a_ptr[3 * a + 2]
            for k in range(ab_ptr[a + 1] - ab_ptr[a]):
                b = ab_idx[ab_ptr[a] + k]
                o = 3 * k
                v0, v1, v2 = a_val[r0 + o], a_val[r0 + o + 1], a_val[r0 + o + 2]
                v3, v4, v5 = a_val[r1 + o], a_val[r1 + o + 1], a_val[r1 + o + 2]
                v6, v7, v8 = a_val[r2 + o], a_val[r2 + o + 1], a_val[r2 + o + 2]
                for f in range(s_ptr[b], s_ptr[b + 1]):
                    w = w_a * s_val[f]
                    q = where[s_idx[f]]
                    buf[q, 0] += w * v0
                    buf[q, 1] += w * v1
                    buf[q, 2] += w * v2
                    buf[q, 3] += w * v3
                    buf[q, 4] += w * v4
                    buf[q, 5] += w * v5
                    buf[q, 6] += w * v6
                    buf[q, 7] += w * v7
                    buf[q, 8] += w * v8
        close_row(i, width, buf, c_scalar_ptr, c_val)


__all__ = ["BlockGalerkin", "GalerkinChain", "block_pattern", "close_row", "full_blocks",
           "in_ranges", "open_row", "row_buffer"]
