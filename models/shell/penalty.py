"""Cluster penalty W_P holding the shell to its embedded target (Remillard & Kry 2013, sec. 4.3).

    W_P = k_P ||H (x - y)||_F^2 = k_P sum_{c, k} (sum_i H_ci (x_ik - y_ik))^2,

with ``H`` a sparse ``(c, n)`` cluster-weight matrix acting on each coordinate and ``y``
``(n, 3)`` the target (``y = B (X_q + u_q)``). Gradient (per coordinate, applying ``H`` then
``H^T``, never forming ``H^T H``)::

    dW_P/dx = 2 k_P H^T (H (x - y)).

The Hessian ``2 k_P (H^T H) kron I3`` is constant but dense within each cluster's support
(``S^2`` vertex blocks for a support of ``S`` vertices), so it is offered two ways:

* assembled: the vertex-level Gram matrix ``H^T H`` (:func:`penalty_gram`) computed once and
  merged into the fixed Hessian pattern (:class:`models.shell.assembly.StencilPattern`);
* low rank: the factor ``G = sqrt(2 k_P) (H kron I3)`` (:func:`penalty_factor`, ``(3c, 3n)``)
  with ``G^T G = 2 k_P (H^T H) kron I3``, for the augmented system
  ``[[A, G^T], [G, -I]]`` that avoids forming ``A + G^T G``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.shell.assembly import TermEval, check_order


@dataclass(frozen=True, eq=False)
class PenaltyOperator:
    """The cluster matrix with its transpose stored once for fast products.

    Attributes:
        H: (c, n) csr_matrix of cluster weights.
        HT: (n, c) csr_matrix, the transpose of H.

    """

    H: sp.csr_matrix
    HT: sp.csr_matrix

    @classmethod
    def from_matrix(cls, H: sp.spmatrix | sp.sparray | np.ndarray,
                    n_vertices: int) -> PenaltyOperator:
        """Validate ``H`` (shape (c, n), finite) and store it with its transpose as CSR."""
        h = sp.csr_matrix(H, dtype=np.float64)
        if h.ndim != 2 or h.shape[1] != n_vertices or h.shape[0] == 0:
            raise InputError(f"H: expected shape (c, {n_vertices}) with c >= 1, got {h.shape}")
        if not np.all(np.isfinite(h.data)):
            raise InputError("H: non-finite cluster weight")
        h.sum_duplicates()
        return cls(H=h, HT=sp.csr_matrix(h.T))

    @property
    def n_clusters(self) -> int:
        """Number of clusters c (rows of H)."""
        return int(self.H.shape[0])


def penalty_term(x: np.ndarray, y: np.ndarray, op: PenaltyOperator, *, order: int = 1,
                 stiffness: float = 1.0) -> TermEval:
    """Value and gradient of ``stiffness * ||H (x - y)||^2`` (no local blocks: see module doc).

    Args:
        x: (n, 3) positions.
        y: (n, 3) target.
        op: The cluster matrix.
        order: 0 value, >= 1 + gradient (the Hessian is constant: :func:`penalty_gram`).
        stiffness: k_P.

    Returns:
        TermEval with ``blocks=None`` and per-cluster energies in ``element_values``.

    """
    check_order(order)
    r = op.H @ (x - y)
    per_cluster = stiffness * np.einsum("ck,ck->c", r, r)
    grad = (2.0 * stiffness * (op.HT @ r)).reshape(-1) if order >= 1 else None
    return TermEval(value=float(per_cluster.sum()), grad=grad, element_values=per_cluster)


def penalty_gram(op: PenaltyOperator) -> sp.csr_matrix:
    """Vertex-level Gram matrix ``H^T H`` (n, n), canonical CSR (computed once)."""
    gram = sp.csr_matrix(op.HT @ op.H)
    gram.sum_duplicates()
    gram.sort_indices()
    return gram


def penalty_factor(op: PenaltyOperator, stiffness: float) -> sp.csr_matrix:
    """Low-rank factor ``G = sqrt(2 k_P) (H kron I3)`` of shape (3c, 3n).

    Row ``3 c + k`` of G acts on coordinate ``k`` (dof ``3 i + k``), so that
    ``G^T G = 2 k_P (H^T H) kron I3`` is the penalty Hessian in the shell's dof order.
    """
    if stiffness < 0:
        raise InputError(f"k_P: must be >= 0, got {stiffness}")
    return sp.csr_matrix(np.sqrt(2.0 * stiffness) * sp.kron(op.H, sp.identity(3), format="csr"))
