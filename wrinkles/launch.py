"""The command that runs this interpreter on N MPI ranks: the venv's ``mpiexec`` first.

The ``mpich`` wheel puts ``mpiexec`` beside the venv's ``python``; an ``mpiexec`` on ``PATH``
may belong to another MPI, whose ranks would not form one communicator with the wheel's
library. Used by the tests, the benchmarks and the paper's scripts (no dolfinx import);
``paper/steps.py`` spells it itself, since importing ``wrinkles`` would cap the BLAS threads
of every step it starts. The CLI uses it to run a serial ``wrinkles run`` of a large shell on
the machine's cores (:func:`relaunch_on_ranks`).
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NoReturn

LAUNCHER_VARIABLES: tuple[str, ...] = ("PMI_SIZE", "PMI_RANK", "PMIX_RANK",
                                       "OMPI_COMM_WORLD_SIZE")
"""Environment variables an MPI launcher sets in the processes it starts (MPICH's Hydra and
other PMI launchers, PMIx, Open MPI): a process that has one was started as MPI ranks."""


def mpiexec_beside() -> str | None:
    """Return the ``mpiexec`` beside this interpreter (the wheel's, the same MPI), else None."""
    beside = Path(sys.executable).with_name("mpiexec")
    return str(beside) if beside.exists() else None


def mpiexec_path() -> str | None:
    """Return the ``mpiexec`` beside this interpreter, else the one on ``PATH``, else None."""
    return mpiexec_beside() or shutil.which("mpiexec")


def python_on_ranks(ranks: int) -> list[str]:
    """Return the command prefix running this interpreter on ``ranks`` MPI ranks.

    ``[mpiexec, "-n", ranks, python]`` for more than one rank, ``[python]`` for one.
    """
    if ranks == 1:
        return [sys.executable]
    return [mpiexec_path() or "mpiexec", "-n", str(ranks), sys.executable]


def under_launcher(environ: Mapping[str, str]) -> bool:
    """Whether ``environ`` is that of a process an MPI launcher started (even on one rank)."""
    return any(name in environ for name in LAUNCHER_VARIABLES)


def relaunch_on_ranks(ranks: int, args: Sequence[str]) -> NoReturn:
    """Replace this process by ``mpiexec -n ranks PROGRAM ARGS`` (does not return).

    ``PROGRAM`` is the console script that runs now (``sys.argv[0]``, so the run records the
    command as the user typed it), else ``python -m wrinkles`` with this interpreter; the
    same environment and working directory. ``args`` are the arguments after the program
    name. Raises ``OSError`` when the launcher is missing.
    """
    launcher = mpiexec_beside()
    if launcher is None:
        raise OSError("no mpiexec beside the interpreter")
    script = sys.argv[0]
    program = [script] if (not script.endswith(".py") and os.path.isfile(script)
                           and os.access(script, os.X_OK)) \
        else [sys.executable, "-m", "wrinkles"]
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(launcher, [launcher, "-n", str(ranks), *program, *args])


__all__ = ["mpiexec_beside", "mpiexec_path", "python_on_ranks", "relaunch_on_ranks",
           "under_launcher"]
