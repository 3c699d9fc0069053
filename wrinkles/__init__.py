"""The ``wrinkles`` application: scenes, runs, output, and the command line.

Importing the package caps the BLAS / OpenMP thread pools at one thread unless the environment
already sets them (``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``): OpenBLAS reads them once,
when numpy is first imported, so they must be set before any module of the application
imports numpy. The shell's own kernels have their own count (``shell.solver.threads``);
BLAS threads on top of them oversubscribe the cores (docs/notes/solver-choice.md).
"""

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
