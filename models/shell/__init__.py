"""Discrete shell (pure numpy / numba / scipy; no dolfinx).

Modules: :mod:`.dofs` (conventions), :mod:`.topology` (edges, hinges), :mod:`.rest` (rest
state), :mod:`.membrane` (W_L, W_A), :mod:`.bending` (W_B), :mod:`.penalty` (W_P),
:mod:`.assembly` (the one sparse assembly), :mod:`.energy` (the composite energy),
:mod:`.stiffness` (physical parameters -> stiffnesses).

Submodules are imported lazily by their users (``from models.shell.energy import
ShellEnergy``) so that importing the package does not compile numba kernels.
"""
