"""The body's Newton systems by CG + algebraic multigrid where the sparse LU costs too much.

A body Newton step solves ``J du = -r`` with ``J`` the Jacobian of the body's energy
(elasticity, inertia ``M / (beta h^2)``, contact penalties; identity Dirichlet rows). The
sparse LU (MUMPS, METIS ordering) costs what its fill costs: a compact ball of 24 000
tetrahedra (13 515 dofs) needs 8.8 GFlop per factorisation, a bunny of 19 379 tetrahedra
(14 010 dofs) 1.4 GFlop, a thin plate (6 303 dofs) 1.4 GFlop. Where the factorisation is
expensive, conjugate gradients preconditioned by PETSc's smoothed-aggregation multigrid
(``PCGAMG``; Adams et al. 2003, "Parallel multigrid smoothing") solve the same system in
10-40 iterations. CG needs ``J`` positive definite; where it is not (a body buckling under
a ball, a contact set pressing a thin plate), CG reports negative curvature and that Newton
step is solved by the LU after all (``fallbacks``).

The choice is made once per solver, after its first factorisation, from MUMPS's count of the
elimination's operations (``RINFOG(1)``, a function of the matrix's pattern and the ordering,
the same on every machine and run): :func:`choose_body_method` against
:data:`ITERATIVE_FLOPS`, the crossover measured in docs/notes/body-linear-solver.md.
"""

from __future__ import annotations

from typing import Any

from models.backend import PETSc, set_from_options

ITERATIVE_FLOPS: float = 1.0e9
"""Operations of one LU factorisation above which the body's steps are solved by CG + GAMG."""
ITERATIVE_RTOL: float = 1.0e-10
"""Relative residual of the CG solves: far below the Newton tolerances, so the Newton
iterations are those of the exact solves."""
DETERMINISTIC: dict[str, str] = {"pc_gamg_mis_k_minimum_degree_ordering": "true"}
"""GAMG's aggregation visits the vertices by degree, not in a random order: the
preconditioner is a function of the matrix."""
MAX_CG_ITERATIONS: int = 500
"""CG iterations before a solve counts as failed (and the LU solves that step)."""


def choose_body_method(lu_flops: float) -> str:
    """Return ``"iterative"`` when one LU factorisation takes more than :data:`ITERATIVE_FLOPS`.

    Args:
        lu_flops: Operations of the elimination, MUMPS ``RINFOG(1)`` (all ranks together).

    """
    return "iterative" if lu_flops > ITERATIVE_FLOPS else "direct"


class IterativeBodySolve:
    """``PCPYTHON`` context: CG + GAMG on the Jacobian, the MUMPS LU where CG fails.

    The outer KSP of the body's SNES is ``preonly`` with this PC, so SNES sees a solve to
    :data:`ITERATIVE_RTOL` either way. GAMG reads AIJ matrices only: a BAIJ Jacobian (the
    direct path's, cheaper to assemble) is copied into AIJ at every set-up; the LU reads the
    Jacobian itself and is factorised only when a CG solve fails.

    Attributes:
        solves: CG solves started.
        fallbacks: Solves CG failed (negative curvature, or no convergence) that the LU made.
        cg_iterations: CG iterations in all.

    """

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.solves = self.fallbacks = self.cg_iterations = 0
        self._matrix: Any = None
        self._aij: Any = None
        self._cg: Any = None
        self._lu: Any = None
        self._lu_current = False

    def setUp(self, pc: Any) -> None:  # noqa: N802 (petsc4py name)
        """Point CG + GAMG at the current Jacobian (an AIJ copy of a blocked one)."""
        matrix = pc.getOperators()[0]
        self._matrix = matrix
        if matrix.getType() in ("seqaij", "mpiaij"):
            self._aij = matrix
        elif self._aij is None or self._aij is matrix:
            self._aij = matrix.convert("aij", PETSc.Mat())  # a new matrix (not in place)
        else:
            matrix.convert("aij", self._aij)  # its values into the copy
        if self._cg is None:
            self._cg = PETSc.KSP().create(matrix.getComm())
            self._cg.setOptionsPrefix(self.prefix + "cg_")
            self._cg.setType("cg")
            self._cg.getPC().setType("gamg")
            self._cg.setTolerances(rtol=ITERATIVE_RTOL, atol=0.0, max_it=MAX_CG_ITERATIONS)
            set_from_options(self._cg, DETERMINISTIC)
        self._cg.setOperators(self._aij)
        self._lu_current = False

    def apply(self, pc: Any, b: Any, x: Any) -> None:  # noqa: ARG002 (petsc4py signature)
        """``x = J^{-1} b`` by CG from zero, by the LU if CG fails."""
        self.solves += 1
        x.set(0.0)
        self._cg.solve(b, x)
        self.cg_iterations += int(self._cg.getIterationNumber())
        if int(self._cg.getConvergedReason()) > 0:
            return
        self.fallbacks += 1
        if self._lu is None:
            self._lu = PETSc.KSP().create(self._matrix.getComm())
            self._lu.setOptionsPrefix(self.prefix + "lu_")
            self._lu.setType("preonly")
            self._lu.getPC().setType("lu")
            self._lu.getPC().setFactorSolverType("mumps")
        if not self._lu_current:
            self._lu.setOperators(self._matrix)
            self._lu_current = True
        self._lu.solve(b, x)

    def destroy(self, pc: Any = None) -> None:  # noqa: ARG002 (petsc4py signature)
        """Free the inner solvers and the AIJ copy (PETSc calls it with the PC it ends)."""
        for ksp in (self._cg, self._lu):
            if ksp is not None:
                ksp.destroy()
        if self._aij is not None and self._aij is not self._matrix:
            self._aij.destroy()
        self._cg = self._lu = self._aij = None


__all__ = ["ITERATIVE_FLOPS", "IterativeBodySolve", "choose_body_method"]
