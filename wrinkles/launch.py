"""The command that runs this interpreter on N MPI ranks: the venv's ``mpiexec`` first.

The ``mpich`` wheel puts ``mpiexec`` beside the venv's ``python``; an ``mpiexec`` on ``PATH``
may belong to another MPI, whose ranks would not form one communicator with the wheel's
library. Used by the tests, the benchmarks and the paper's scripts (no dolfinx import);
``paper/steps.py`` spells it itself, since importing ``wrinkles`` would cap the BLAS threads
of every step it starts.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path


def mpiexec_path() -> str | None:
    """Return the ``mpiexec`` beside this interpreter, else the one on ``PATH``, else None."""
    beside = Path(sys.executable).with_name("mpiexec")
    return str(beside) if beside.exists() else shutil.which("mpiexec")


def python_on_ranks(ranks: int) -> list[str]:
    """Return the command prefix running this interpreter on ``ranks`` MPI ranks.

    ``[mpiexec, "-n", ranks, python]`` for more than one rank, ``[python]`` for one.
    """
    if ranks == 1:
        return [sys.executable]
    return [mpiexec_path() or "mpiexec", "-n", str(ranks), sys.executable]


__all__ = ["mpiexec_path", "python_on_ranks"]
