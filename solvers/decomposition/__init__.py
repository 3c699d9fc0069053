"""Acceleration by decomposition (MISSION.md section 7, section 5 of the draft).

Modules: :mod:`.patches` (disjoint vertex sets -> patches, the draft's four conditions,
merging down to the number of workers), :mod:`.patch_energy` (the global energy restricted
to one patch's owned vertices, everything else held fixed), :mod:`.block` (block Jacobi /
Gauss-Seidel outer iteration with a pluggable exchange), :mod:`.parallel` (the MPI
exchanges: client-server and neighbour-to-neighbour), :mod:`.distributed` (the monolithic
Newton step with a distributed PETSc MPIAIJ Hessian and MUMPS / SuperLU_dist, assembled
penalty, redundant evaluation), :mod:`.split_newton` (the monolithic Newton split by stencils
across ranks with the low-rank penalty in a distributed augmented system, MUMPS LDL^T: the
scalable reference), :mod:`.demo` (the compressed-plate wrinkling problem and its
warm-started frame, for the tests and benchmark).
"""
