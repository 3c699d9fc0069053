"""Collective error handling: serial work on rank 0 whose errors every rank raises.

Reading a file or running gmsh happens on rank 0 only; if it fails with a ``WrinklesError``
while the other ranks wait for its result, they must fail too, with the same message, instead
of waiting forever in the next collective call. :func:`on_root` broadcasts the outcome.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import cast

from meshes.errors import WrinklesError
from models.backend import MPI
from wrinkles.launch import under_launcher


def on_root[T](comm: MPI.Comm, make: Callable[[], T]) -> T | None:
    """Run ``make()`` on rank 0 only; re-raise its ``WrinklesError`` on every rank.

    Returns:
        ``make()``'s value on rank 0, ``None`` elsewhere.

    """
    value: T | None = None
    failure: tuple[type[WrinklesError], str] | None = None
    if comm.rank == 0:
        try:
            value = make()
        except WrinklesError as exc:
            failure = (type(exc), str(exc))
    failure = comm.bcast(failure, root=0)
    if failure is not None:
        raise failure[0](failure[1])
    return value


def world_root() -> bool:
    """Whether this process is rank 0 of ``COMM_WORLD``.

    A process no MPI launcher started is alone, so rank 0, without loading the stack
    (:func:`wrinkles.launch.under_launcher`); a launched one asks MPI.
    """
    return not under_launcher(os.environ) or MPI.COMM_WORLD.rank == 0


def shared[T](comm: MPI.Comm, make: Callable[[], T]) -> T:
    """Run ``make()`` on rank 0 (errors raised everywhere) and broadcast its value."""
    return cast(T, comm.bcast(on_root(comm, make), root=0))
