"""The one adapter between this code and the dolfinx 0.11 / PETSc / MPI stack.

Every other module imports ``MPI``, ``PETSc``, ``dolfinx``, ``ufl`` and ``basix`` from here,
never directly: the ``dolfinx-solver-real`` wheel requires ``import dolfinx_solver`` before
mpi4py, petsc4py or dolfinx are loaded (it orders one MPI runtime ahead of the compiled
bindings), and keeping the dolfinx-version-specific calls in this module means a dolfinx
upgrade touches one file.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (must precede mpi4py, petsc4py and dolfinx)

import basix  # noqa: E402
import dolfinx  # noqa: E402
import dolfinx.fem  # noqa: E402
import dolfinx.fem.petsc  # noqa: E402
import dolfinx.io  # noqa: E402
import dolfinx.mesh  # noqa: E402
import ufl  # noqa: E402
from mpi4py import MPI  # noqa: E402
from petsc4py import PETSc  # noqa: E402

__all__ = ["MPI", "PETSc", "basix", "dolfinx", "ufl", "DOLFINX_VERSION"]

DOLFINX_VERSION: str = dolfinx.__version__
