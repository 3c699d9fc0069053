"""Acceleration by decomposition (MISSION.md section 7, section 5 of the draft).

Modules: :mod:`.patches` (disjoint vertex sets -> patches, the draft's four conditions,
merging or bisecting down to the number of workers), :mod:`.patch_energy` (the global energy
restricted to one patch's owned vertices, everything else held fixed), :mod:`.block` (block
Jacobi / Gauss-Seidel outer iteration with a pluggable exchange), :mod:`.parallel` (the MPI
exchanges: client-server and neighbour-to-neighbour), :mod:`.distributed` (the monolithic
Newton step with a distributed PETSc MPIAIJ Hessian and MUMPS / SuperLU_dist, assembled
penalty, redundant evaluation), :mod:`.split_newton` (the monolithic Newton split by stencils
across ranks, the shell solver of ``mpiexec -n N wrinkles run``: the low-rank penalty in a
distributed augmented system factorised by MUMPS LDL^T, or :mod:`.split_multigrid`, CG and
geometric multigrid over PETSc with the wrinkle-phase space of :mod:`.split_phase`),
:mod:`.demo` (the compressed-plate wrinkling problem and its warm-started frame, for the tests
and benchmark).
"""
