"""Decomposed shell solve over MPI: patches on ranks, two exchange arrangements.

Every rank builds the same :class:`PatchSet` (deterministic), keeps the patches assigned to it
(largest first onto the least loaded rank, by owned vertex count) and runs the
:class:`BlockSolver` outer iteration. Values move in one of two ways (``exchange``):

* ``"client_server"`` (the draft's arrangement): after each sweep every rank sends its owned
  values to rank 0 (gather), which assembles the whole state and broadcasts it; reductions
  (global gradient, Anderson Gram matrix) and error flags also go through rank 0;
* ``"neighbour"``: each rank sends only the owned values other ranks' patches read (their
  halo), point to point (``Isend`` / ``Irecv``) to the neighbouring ranks; reductions are an
  ``Allreduce`` carrying an error flag, followed by an ``allgather`` of the messages only when
  a flag is set.

Either way every rank learns about a failed patch solve at the next exchange and raises the
same :class:`SolverError`, so no rank is left waiting (entry points turn it into exit code 2).
The wall-time cap ``BlockOptions.max_seconds`` is agreed through the same reduction
(``agree``: one scalar per outer iteration), so all ranks stop after the same outer iteration.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from meshes.errors import InputError, SolverError
from models.backend import MPI
from solvers.decomposition.block import BlockOptions, BlockReport, BlockSolver, patch_colours
from solvers.decomposition.patch_energy import PatchEnergy, ShellProblem
from solvers.decomposition.patches import PatchSet, build_patches

ExchangeMode = Literal["client_server", "neighbour"]
_TAG = 731


@dataclass(frozen=True)
class ParallelOptions:
    """Options of the MPI decomposed solve.

    Attributes:
        exchange: "client_server" (gather to rank 0 and broadcast) or "neighbour" (halo
            values point to point).
        patches_per_rank: Patches per rank (the sets are merged down to ranks x this).
        block: Options of the outer block iteration.

    """

    exchange: ExchangeMode = "neighbour"
    patches_per_rank: int = 1
    block: BlockOptions = field(default_factory=BlockOptions)

    def __post_init__(self) -> None:
        if self.exchange not in ("client_server", "neighbour"):
            raise InputError(f"ParallelOptions.exchange: expected 'client_server' or "
                             f"'neighbour', got {self.exchange!r}")
        if self.patches_per_rank < 1:
            raise InputError(f"ParallelOptions.patches_per_rank: must be >= 1, got "
                             f"{self.patches_per_rank}")


def _raise_if(messages: Sequence[str | None]) -> None:
    """Raise SolverError joining the messages of the ranks that failed."""
    failed = [f"rank {r}: {m}" for r, m in enumerate(messages) if m]
    if failed:
        raise SolverError("decomposed solve stopped: " + "; ".join(failed))


def _owned_values(x: np.ndarray, patches: Sequence[PatchEnergy]) -> np.ndarray:
    """Owned rows of x, in patch order, flat."""
    if not patches:
        return np.zeros(0)
    return np.concatenate([x[p.interior].reshape(-1) for p in patches])


class ClientServerExchange:
    """Rank 0 gathers owned values and reductions, assembles, broadcasts (the draft's CS)."""

    def __init__(self, comm: Any, patches: Sequence[PatchEnergy]) -> None:
        self.comm = comm
        owned = (np.concatenate([p.interior for p in patches]) if patches
                 else np.zeros(0, np.int64))
        self._ids = comm.gather(owned, root=0)

    def agree(self, values: np.ndarray, error: str | None) -> np.ndarray:
        """Sum over ranks at rank 0, broadcast the sum and every error message."""
        gathered = self.comm.gather((np.asarray(values, dtype=np.float64), error), root=0)
        result = None
        if self.comm.rank == 0:
            result = (np.sum([v for v, _ in gathered], axis=0), [e for _, e in gathered])
        total, messages = self.comm.bcast(result, root=0)
        _raise_if(messages)
        return total

    def share(self, x: np.ndarray, patches: Sequence[PatchEnergy]) -> None:
        """Gather owned values at rank 0, write them into its x, broadcast the whole x."""
        gathered = self.comm.gather(_owned_values(x, patches), root=0)
        if self.comm.rank == 0:
            for ids, vals in zip(self._ids, gathered, strict=True):
                x[ids] = vals.reshape(-1, 3)
        self.comm.Bcast(x, root=0)


class NeighbourExchange:
    """Owned halo values point to point between neighbouring ranks; Allreduce with a flag."""

    def __init__(self, comm: Any, rank_of_vertex: np.ndarray,
                 patches: Sequence[PatchEnergy]) -> None:
        self.comm = comm
        halo = (np.unique(np.concatenate([p.halo for p in patches])) if patches
                else np.zeros(0, np.int64))
        halo = halo[rank_of_vertex[halo] != comm.rank]
        wanted = [halo[rank_of_vertex[halo] == r] for r in range(comm.size)]
        asked = comm.alltoall(wanted)
        self.recv = {r: ids for r, ids in enumerate(wanted) if ids.size}
        self.send = {r: ids for r, ids in enumerate(asked) if ids.size}

    @property
    def neighbours(self) -> list[int]:
        """Ranks this rank exchanges values with."""
        return sorted(set(self.recv) | set(self.send))

    def agree(self, values: np.ndarray, error: str | None) -> np.ndarray:
        """Allreduce ``[values, flag]``; on a flag allgather the messages and raise."""
        local = np.append(np.asarray(values, dtype=np.float64), 1.0 if error else 0.0)
        total = np.empty_like(local)
        self.comm.Allreduce(local, total, op=MPI.SUM)
        if total[-1] > 0:
            _raise_if(self.comm.allgather(error))
        return total[:-1]

    def share(self, x: np.ndarray, patches: Sequence[PatchEnergy]) -> None:
        """Send owned values neighbours read; receive the halo values this rank reads."""
        buffers = {r: np.empty((ids.size, 3)) for r, ids in self.recv.items()}
        requests = [self.comm.Irecv(buffers[r], source=r, tag=_TAG) for r in self.recv]
        outgoing = {r: np.ascontiguousarray(x[ids]) for r, ids in self.send.items()}
        requests += [self.comm.Isend(outgoing[r], dest=r, tag=_TAG) for r in self.send]
        MPI.Request.Waitall(requests)
        for r, ids in self.recv.items():
            x[ids] = buffers[r]


def assign_patches(sizes: np.ndarray, n_ranks: int) -> np.ndarray:
    """Rank of each patch: largest patch first onto the least loaded rank (LPT)."""
    load = np.zeros(n_ranks)
    rank = np.zeros(sizes.size, dtype=np.int64)
    for p in np.argsort(-sizes, kind="stable"):
        rank[p] = int(np.argmin(load))
        load[rank[p]] += sizes[p]
    return rank


@dataclass(frozen=True, eq=False)
class ParallelResult:
    """Outcome of :func:`parallel_block_solve` (the same on every rank).

    Attributes:
        x: (n, 3) final positions (gathered on every rank).
        report: The outer iteration report (times are this rank's).
        patches: The patch set.
        patch_rank: Rank of each patch.
        colours: Colour of each patch (all 0 for Jacobi).

    """

    x: np.ndarray
    report: BlockReport
    patches: PatchSet
    patch_rank: np.ndarray
    colours: np.ndarray


def _global_colours(comm: Any, mine: list[int], energies: list[PatchEnergy], n_patches: int,
                    n_vertices: int, method: str) -> np.ndarray:
    """Colouring of all patches from every rank's owned/halo sets (identical on all ranks)."""
    if method == "jacobi":
        return np.zeros(n_patches, dtype=np.int64)
    pieces = comm.allgather([(p, e.interior, e.halo) for p, e in zip(mine, energies,
                                                                     strict=True)])
    by_patch = {p: (i, h) for piece in pieces for p, i, h in piece}
    return patch_colours([by_patch[p][0] for p in range(n_patches)],
                         [by_patch[p][1] for p in range(n_patches)], n_vertices)


def _gather_x(comm: Any, x: np.ndarray, energies: Sequence[PatchEnergy]) -> np.ndarray:
    """Assemble the owned values of every rank into one (n, 3) array on every rank."""
    ids = np.concatenate([e.interior for e in energies]) if energies else np.zeros(0, np.int64)
    out = np.array(x, copy=True)
    for r_ids, r_vals in comm.allgather((ids, _owned_values(x, energies))):
        out[r_ids] = r_vals.reshape(-1, 3)
    return out


def _build_energies(comm: Any, problem: ShellProblem, patches: PatchSet,
                    mine: list[int]) -> list[PatchEnergy]:
    """Build this rank's patch energies; a failure on any rank stops all of them."""
    energies, error = [], None
    try:
        energies = [PatchEnergy(problem, patches.patches[p].interior) for p in mine]
    except Exception as err:  # noqa: BLE001 - must reach every rank
        error = f"patch setup failed: {type(err).__name__}: {err}"
    _raise_if(comm.allgather(error))
    return energies


def parallel_block_solve(problem: ShellProblem, partition: np.ndarray, x0: np.ndarray,
                         options: ParallelOptions | None = None,
                         comm: Any = None) -> ParallelResult:
    """Decomposed solve over the ranks of ``comm`` (see the module docstring).

    Args:
        problem: The global shell problem (the same on every rank).
        partition: (n,) disjoint vertex sets (``Clusters.partition``).
        x0: (n, 3) start.
        options: Exchange arrangement, patches per rank, block options.
        comm: MPI communicator (default COMM_WORLD).

    Returns:
        :class:`ParallelResult` with x on every rank.

    Raises:
        SolverError: a patch solve failed on any rank (raised on all ranks).

    """
    opts = options or ParallelOptions()
    comm = comm if comm is not None else MPI.COMM_WORLD
    patches = build_patches(problem.topology, partition, comm.size * opts.patches_per_rank)
    patch_rank = assign_patches(patches.sizes(), comm.size)
    mine = np.flatnonzero(patch_rank == comm.rank).tolist()
    energies = _build_energies(comm, problem, patches, mine)
    n = problem.topology.n_vertices
    colours = _global_colours(comm, mine, energies, patches.n_patches, n, opts.block.method)
    exchange: ClientServerExchange | NeighbourExchange = (
        ClientServerExchange(comm, energies) if opts.exchange == "client_server"
        else NeighbourExchange(comm, patch_rank[patches.owner], energies))
    solver = BlockSolver(energies, mine, colours[mine], int(colours.max()) + 1, exchange,
                         opts.block)
    x, report = solver.solve(np.asarray(x0, dtype=np.float64))
    return ParallelResult(x=_gather_x(comm, x, energies), report=report, patches=patches,
                          patch_rank=patch_rank, colours=colours)
