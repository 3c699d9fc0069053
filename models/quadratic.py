"""A quadratic energy term ``E(u) = 1/2 u^T K u - c^T u + e0`` on a dolfinx dof vector.

The embedded shell's cluster penalty ``k_P ||H (x - B (X + u))||^2`` with the shell ``x`` held
fixed is such a term in the body displacement ``u`` (:mod:`models.coupling`); the body's
Newton solver (:mod:`solvers.body_newton`) adds it to the objective, residual and Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class QuadraticTerm:
    """An extra energy ``E(u) = 1/2 u^T K u - c^T u + e0`` of the Newton problem.

    Attributes:
        K: symmetric PETSc matrix in the (global) dof layout of ``u`` (its Hessian).
        c: PETSc vector in the same layout (``-c`` is its gradient at ``u = 0``).
        e0: constant energy [J] (makes ``E`` the physical value, e.g. ``k_P |H d|^2``).

    """

    K: Any
    c: Any
    e0: float = 0.0

    def value(self, u: Any) -> float:
        """``1/2 u^T K u - c^T u + e0`` for a PETSc vector ``u`` (collective)."""
        Ku = self.K.createVecLeft()
        self.K.mult(u, Ku)
        value = 0.5 * float(Ku.dot(u).real) - float(self.c.dot(u).real) + self.e0
        Ku.destroy()
        return value

    def gradient(self, u: Any) -> Any:
        """Return a new PETSc vector ``K u - c`` (collective)."""
        g = self.K.createVecLeft()
        self.K.mult(u, g)
        g.axpy(-1.0, self.c)
        return g
