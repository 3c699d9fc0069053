"""Threads for the shell's element kernels: a race-free split of each stencil array.

The fused kernels (:mod:`models.shell.membrane`, :mod:`models.shell.bending`,
:mod:`models.shell.barrier`) add each stencil's gradient and Hessian block into shared arrays.
A stencil only writes the gradient entries and the Hessian rows of its own vertices
(:func:`models.shell.assembly.scatter_block`), so two stencils without a common vertex never
write the same number. :func:`vertex_parts` splits the vertices into ``threads`` bands (equal
contiguous ranges of a reverse Cuthill-McKee order of the vertex graph: level sets of a
breadth-first search, Cuthill & McKee 1969); :class:`StencilSchedule` gives thread t the
stencils whose vertices all lie in band t and keeps the stencils that straddle two bands (the
interface, O(sqrt n) of them on a surface) for afterwards. :meth:`StencilSchedule.run` runs
the chunks concurrently on a shared thread pool (the kernels are compiled ``nogil``) and then
the interface on the calling thread, so the result is deterministic for a given thread count.

The same bands serve only the element kernels, whose calls are long: a Python thread pool is
cheap there. The multigrid's short products split their rows with :func:`balanced_cuts` and
run them in numba ``prange`` loops instead (:mod:`solvers.multigrid`), since the pool's GIL
hand-offs cost about a millisecond per call.

With one thread the schedule is the identity (one chunk ``0 .. m - 1``, no interface): the
same additions in the same order as the plain loop, bitwise. With several, each sum (energy,
gradient entry, Hessian entry) is added in another order: round-off differences only.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import reverse_cuthill_mckee

from meshes.errors import InputError
from models.shell.reorder import vertex_adjacency

_POOLS: dict[int, ThreadPoolExecutor] = {}


def check_threads(threads: int, name: str = "threads") -> int:
    """Return ``threads`` as an int, or raise InputError naming ``name`` unless it is >= 1."""
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InputError(f"{name}: expected an integer >= 1, got {threads!r}")
    return int(threads)


def thread_pool(threads: int) -> ThreadPoolExecutor:
    """Return the process-wide pool of ``threads`` workers (created once per size)."""
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(max_workers=threads,
                                             thread_name_prefix="wrinkles-kernel")
    return _POOLS[threads]


def vertex_parts(faces: np.ndarray, n_vertices: int, threads: int) -> np.ndarray:
    """Band of each vertex (n,): ``threads`` equal ranges of an RCM order of the face edges.

    The order is :mod:`models.shell.reorder`'s (RCM on :func:`vertex_adjacency`).
    """
    threads = check_threads(threads)
    if threads == 1 or n_vertices == 0:
        return np.zeros(n_vertices, dtype=np.int64)
    order = reverse_cuthill_mckee(vertex_adjacency(faces, n_vertices), symmetric_mode=True)
    parts = np.empty(n_vertices, dtype=np.int64)
    parts[order] = np.arange(n_vertices) * threads // n_vertices
    return parts


@dataclass(frozen=True, eq=False)
class StencilSchedule:
    """Which stencils each thread runs (see the module docstring).

    Attributes:
        chunks: Per thread, the int64 indices of the stencils inside its band (ascending).
        interface: Indices of the stencils across bands, run after the chunks.

    """

    chunks: tuple[np.ndarray, ...]
    interface: np.ndarray

    @classmethod
    def serial(cls, m: int) -> StencilSchedule:
        """One chunk of every stencil in order (the plain loop)."""
        return cls((np.arange(m, dtype=np.int64),), np.empty(0, dtype=np.int64))

    @classmethod
    def build(cls, stencils: np.ndarray, parts: np.ndarray) -> StencilSchedule:
        """Split ``stencils`` (m, s) by the bands ``parts`` (n,) of their vertices."""
        threads = int(parts.max()) + 1 if parts.size else 1
        if threads == 1:
            return cls.serial(stencils.shape[0])
        owner = parts[stencils]
        inside = np.all(owner == owner[:, :1], axis=1)
        chunks = tuple(np.flatnonzero(inside & (owner[:, 0] == t)) for t in range(threads))
        return cls(chunks, np.flatnonzero(~inside))

    @property
    def threads(self) -> int:
        """Number of concurrent chunks."""
        return len(self.chunks)

    def run(self, kernel: Callable[[np.ndarray], float]) -> float:
        """Sum of ``kernel(index)`` over the chunks (concurrently) and then the interface.

        ``kernel`` must release the GIL (a ``nogil`` numba kernel) to run in parallel and
        write only the entries of the stencils it is given.
        """
        if self.threads == 1:
            total = kernel(self.chunks[0])
        else:
            total = sum(thread_pool(self.threads).map(kernel, self.chunks))
        return total + kernel(self.interface) if self.interface.size else total


def balanced_cuts(indptr: np.ndarray, threads: int) -> np.ndarray:
    """Row boundaries (threads + 1,) splitting a CSR-like ``indptr`` into equal-work ranges."""
    threads = check_threads(threads)
    rows = indptr.size - 1
    targets = np.arange(threads + 1) * (int(indptr[-1]) / threads)
    cuts = np.searchsorted(indptr, targets).clip(0, rows)
    cuts[0], cuts[-1] = 0, rows
    return np.maximum.accumulate(cuts).astype(np.int64)

