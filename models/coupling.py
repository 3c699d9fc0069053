"""Two-way coupling of the embedded shell with the coarse body (Remillard & Kry 2013, sec. 4.4).

The shell is held by the cluster penalty ``W_P = k_P ||H (x - y)||^2`` to its target
``y = B (X_q + u_q)``. The penalty pulls on the target with the force

    f = -dW_P/dy = 2 k_P H^T H (x - y)        (n, 3), one row per shell vertex,

and, since ``dy/du_q = B``, on the body's degrees of freedom with the nodal force
``F = B^T f`` (``add_transpose_to_function``). Because every row of B sums to 1, the total
force is conserved: ``sum_j F_j = sum_i f_i`` (per component).

The body minimises an energy, so a given nodal force enters as the potential ``-F . u``:
:meth:`solvers.body.Body.set_nodal_load` (``-int g . u dX`` with ``M g = F``); the total force
actually applied is :meth:`solvers.body.Body.applied_load`, ``int g dX``. Two-way coupling
does not lag it as a load: the penalty is part of the coupled energy (:mod:`solvers.monolithic`)
or, in the fixed point, of the body's energy (:class:`PenaltyCoupling`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from models.backend import PETSc, dolfinx
from models.embedding.embedding import Embedding, add_transpose_to_function
from models.quadratic import QuadraticTerm
from models.shell.penalty import PenaltyOperator, penalty_gram
from models.shell.penalty import penalty_term as shell_penalty_term


def penalty_force(H: sp.csr_matrix | PenaltyOperator, k_P: float, x: np.ndarray,
                  y: np.ndarray) -> np.ndarray:
    """Force of the cluster penalty on the target, ``f = -dW_P/dy = 2 k_P H^T H (x - y)``.

    Since ``W_P`` depends on ``x - y`` only, ``-dW_P/dy = dW_P/dx``: the gradient of
    :func:`models.shell.penalty.penalty_term`, reused here.

    Args:
        H: ``(c, n)`` cluster matrix, or its :class:`PenaltyOperator` (no transpose per call).
        k_P: penalty stiffness.
        x: ``(n, 3)`` shell positions.
        y: ``(n, 3)`` target.

    Returns:
        ``(n, 3)`` forces (energy / length).

    """
    x, y = np.asarray(x), np.asarray(y)
    op = H if isinstance(H, PenaltyOperator) else PenaltyOperator.from_matrix(H, x.shape[0])
    grad = shell_penalty_term(x, y, op, order=1, stiffness=k_P).grad
    assert grad is not None  # order 1
    return grad.reshape(-1, 3)


@dataclass(frozen=True, eq=False)
class PenaltyCoupling:
    """The constant part of the implicit coupling term, built once per run (collective).

    ``K = 2 k_P (B^T H^T H B) (x) I_3`` and ``M = 2 k_P B^T H^T H`` depend on the embedding,
    the clusters and ``k_P`` only, so the two-way iteration assembles them once and forms
    only ``c = M d`` per iteration.

    Attributes:
        K: PETSc matrix of this rank's owned rows (shared by every :meth:`term`: do not
            destroy it while the coupling is in use).
        M: ``(n_b, n)`` scipy matrix ``2 k_P B^T H^T H`` (rows: body nodes).
        op: the cluster matrix with its transpose.
        k_P: penalty stiffness.
        rows: ``(lo, hi)`` owned block range of the body space.
        bs: block size of the body space (3).

    """

    K: Any
    M: sp.csr_matrix
    op: PenaltyOperator
    k_P: float
    rows: tuple[int, int]
    bs: int

    @classmethod
    def build(cls, emb: Embedding, H: sp.csr_matrix, k_P: float, V: Any) -> PenaltyCoupling:
        """Assemble ``K`` and ``M`` for the body space ``V`` (collective)."""
        B = emb.global_matrix()
        op = PenaltyOperator.from_matrix(H, B.shape[0])
        M = ((2.0 * k_P) * (B.T @ penalty_gram(op))).tocsr()
        K = sp.kron(M @ B, sp.identity(3), format="csr")
        lo, hi = V.dofmap.index_map.local_range
        bs = V.dofmap.index_map_bs
        owned = K[lo * bs:hi * bs].tocsr()
        owned.sort_indices()
        n_global = K.shape[0]
        mat = PETSc.Mat().createAIJ(size=((owned.shape[0], n_global), (owned.shape[0], n_global)),
                                    csr=(owned.indptr.astype(PETSc.IntType),
                                         owned.indices.astype(PETSc.IntType), owned.data),
                                    comm=V.mesh.comm)
        mat.assemble()
        return cls(mat, M, op, float(k_P), (int(lo), int(hi)), int(bs))

    def term(self, d: np.ndarray) -> QuadraticTerm:
        """Return the quadratic term of the shell displacement ``d = x - X_T`` ((n, 3))."""
        return self.load_term(self.load(d), self.energy(d))

    def load(self, d: np.ndarray) -> np.ndarray:
        """Return ``c = M d`` on all body nodes ((n_b, 3)): all the body sees of the shell."""
        return np.asarray(self.M @ d)

    def load_term(self, c: np.ndarray, e0: float) -> QuadraticTerm:
        """Return the term ``1/2 u^T K u - c^T u + e0`` for a given load ``c`` ((n_b, 3)).

        ``term(d)`` is ``load_term(load(d), k_P ||H d||^2)``; the two-way iteration passes an
        accelerated ``c`` (a combination of previous ``M d``) here.
        """
        lo, hi = self.rows
        vec = self.K.createVecLeft()
        vec.array[:] = np.asarray(c)[lo:hi].reshape(-1)
        return QuadraticTerm(self.K, vec, float(e0))

    def energy(self, d: np.ndarray) -> float:
        """Return the constant ``e0 = k_P ||H d||^2`` of the term of ``d``."""
        hd = self.op.H @ d
        return float(self.k_P * np.sum(hd * hd))


def penalty_term(emb: Embedding, H: sp.csr_matrix, k_P: float, d: np.ndarray,
                 V: Any) -> QuadraticTerm:
    """Return the cluster penalty, shell fixed, as a quadratic energy of the body's dofs.

    With ``d = x - X_T`` (shell minus rest positions) and ``y = X_T + B u``,

        E(u) = k_P ||H (d - B u)||^2 = 1/2 u^T K u - c^T u + e0,
        K = 2 k_P B^T H^T H B,   c = 2 k_P B^T H^T H d,   e0 = k_P ||H d||^2,

    per component (``K`` acts on the 3 components alike: ``K (x) I_3`` in the interleaved
    dof layout ``3 b + k``). ``-dE/du = B^T f`` with ``f`` of :func:`penalty_force`, so the
    total force on the body equals ``sum_i f_i``. Collective; each rank sets its owned rows.
    A loop over many ``d`` should build :class:`PenaltyCoupling` once and call its ``term``.

    Args:
        emb: B for the body's space ``V``.
        H: ``(c, n)`` cluster matrix.
        k_P: penalty stiffness.
        d: ``(n, 3)`` shell displacement ``x - X_T``.
        V: the body's vector function space.

    """
    return PenaltyCoupling.build(emb, H, k_P, V).term(d)


def body_force_function(emb: Embedding, forces: np.ndarray, V: Any) -> Any:
    """Nodal forces ``B^T f`` as a dolfinx Function on ``V`` (collective)."""
    F = dolfinx.fem.Function(V, name="nodal_force")
    add_transpose_to_function(emb, forces, F)
    return F


__all__ = ["PenaltyCoupling", "body_force_function", "penalty_force", "penalty_term"]
