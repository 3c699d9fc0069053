r"""The two-way joint Newton solve of body and shell with the shell split over the ranks.

The distributed counterpart of :class:`solvers.monolithic.CoupledEnergy` with
:class:`solvers.joint_krylov.JointKrylovSystem`. The unknowns are ``z = (x, u)``, the shell
positions and the body's dofs, and the energy ``E(x, u) = Pi(u) + W(x; X_T + B u)``
(:mod:`solvers.monolithic`). The shell part is held as in
:class:`~solvers.decomposition.split_newton.SplitNewtonSolver`: every rank evaluates the
stencils of its own vertices (:class:`~.split_newton.SplitShellEnergy`) and holds their rows
of ``K_x``; the coarse body's gradient and Hessian are on every rank
(:class:`solvers.monolithic.BodyUnknowns`), as is every full vector the Newton decides on.

The joint matrix ``M = blockdiag(K_x, K_u) + F^T F + tau I``, ``F = [G, -G B]``, is applied
as

.. math::  M \begin{bmatrix} p_x \\ p_u \end{bmatrix} =
           \begin{bmatrix} (K_x + \tau I) p_x + s \\ (K_u + \tau I) p_u - B^T s \end{bmatrix},
           \qquad s = G^T G (p_x - B p_u),

``B`` with its pinned body columns zero: one distributed product with ``G`` and ``G^T`` (the
fine level's of :class:`~.split_multigrid.SplitMultigridSystem`) on the rank's rows, and one
sum over ranks of the ``3 n_b`` numbers ``B^T s``. The CG vectors are a rank's owned shell
dofs followed by all body dofs (the same on every rank); an inner product sums the shell
parts over ranks and adds the body part. The preconditioner is the serial one's,
``diag(V_x, M_uu^{-1})``: one V-cycle of the distributed shell multigrid and the body block
factorised on every rank (:class:`solvers.joint_krylov.BodyBlock`). Every rank takes the same
steps; the iterates differ from the serial solve's by round-off (sums in another order).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import MPI
from solvers.decomposition.split_multigrid import SplitMultigridSystem
from solvers.decomposition.split_newton import OwnedRows, SplitNewtonSolver, SplitShellEnergy
from solvers.joint_krylov import JointCG, ShellBlock
from solvers.linear import FactorReport
from solvers.monolithic import CoupledEnergy, CoupledEval
from solvers.multigrid import MultigridOptions


@dataclass(frozen=True, eq=False)
class JointRows:
    """The joint Hessian as one rank holds it: its rows of ``K_x`` and all of ``K_u``.

    Stands in for the joint Hessian in the shell Newton, which reads only its diagonal (the
    shift ladder's scale): ``diag(K_x)`` (allgathered) then ``diag(K_u)``, as the serial
    joint Hessian's.
    """

    shell: OwnedRows
    body: sp.csr_matrix

    def diagonal(self) -> np.ndarray:
        """Return the full diagonal (3 (n + n_b),), the same on every rank."""
        return np.concatenate([self.shell.full_diagonal, self.body.diagonal()])


class SplitCoupledEnergy:
    """``E(x, u)`` with the shell split over the ranks (the shell Newton's energy interface).

    Args:
        shell: The split shell energy (its penalty Hessian is carried by ``G``).
        joint: The serial coupled energy of the same shell, body and ``B``: its maps
            (``split``, ``target``), the body's unknowns and the penalty operator are used;
            its shell energy is not evaluated.

    """

    def __init__(self, shell: SplitShellEnergy, joint: CoupledEnergy) -> None:
        if joint.factor is None:
            raise InputError("SplitCoupledEnergy: the shell's penalty must be the low-rank "
                             "factor G (shell.energy.penalty_hessian = 'low_rank')")
        self.shell, self.joint = shell, joint
        self.n = joint.n

    @property
    def n_vertices(self) -> int:
        """Rows of ``z``: shell vertices plus body nodes."""
        return self.joint.n_vertices

    def value(self, x: np.ndarray) -> float:
        """Return ``E(z)`` at the stacked ``x = z`` (collective)."""
        return self.evaluate(x, order=0).value

    def evaluate(self, x: np.ndarray, order: int = 2, hessian: Any = None) -> CoupledEval:
        """Return ``E``, its full gradient and this rank's Hessian rows at ``x = z`` (collective).

        The value and gradient are the same on every rank; ``hess`` is a :class:`JointRows`
        and ``blocks`` its ``(K_x rows, K_u)``.
        """
        ev, value, grad, k_u = self.joint.evaluate_with(self.shell, x, order, hessian)
        if order < 2:
            return CoupledEval(value, grad, None, None)
        assert isinstance(ev.hess, OwnedRows) and k_u is not None  # order 2, split energy
        return CoupledEval(value, grad, JointRows(ev.hess, k_u), None, (ev.hess, k_u))


class SplitJointKrylov(JointCG):
    """Block-preconditioned CG for the joint matrix with the shell split (module docstring).

    Args:
        shell: The distributed shell multigrid without the phase space (its hierarchy ends at
            the split energy's fine level).
        energy: The split coupled energy (ownership, ``B`` and ``F_u``).

    """

    def __init__(self, shell: SplitMultigridSystem, energy: SplitCoupledEnergy) -> None:
        if shell.phase is not None:
            raise InputError("SplitJointKrylov: the shell multigrid must run without the "
                             "phase space (its V-cycle is the shell block's preconditioner)")
        joint = energy.joint
        super().__init__(shell, joint.body_factor)
        self.split, self.comm = energy.shell, energy.shell.comm
        self.owned = shell.levels[-1].owned
        self.m = int(self.owned.size)
        self.n = 3 * joint.n
        self.b_rows = sp.csr_matrix(joint.embedding_free[self.owned])
        self.b_rows_t = sp.csr_matrix(self.b_rows.T)
        a = shell.fine_matrix
        self._vecs = (a.createVecs()[1], a.createVecs()[1], a.createVecs()[1])
        self._g = shell.fine_penalty  # G exists: SplitCoupledEnergy refuses a shell without it
        self._g_vec = self._g.createVecs()[1]

    def _shell_setup(self, k_x: Any, tau: float) -> FactorReport:
        """Set the distributed shell multigrid up for ``K_x + G^T G + tau I``."""
        return self.shell.factorize(ShellBlock(k_x, None), tau)

    def _penalty(self, d: np.ndarray) -> np.ndarray:
        """``s = G^T G d`` on this rank's rows (collective)."""
        v, s, _ = self._vecs
        v.setArray(d)
        self._g.mult(v, self._g_vec)
        self._g.multTranspose(self._g_vec, s)
        return s.getArray(readonly=True).copy()

    def apply(self, v: np.ndarray) -> np.ndarray:
        """Return ``M v`` (CG vectors; collective)."""
        assert self._tau is not None  # factorize() succeeded first (internal invariant)
        p_x, p_u = v[:self.m], v[self.m:]
        s = self._penalty(p_x - self.b_rows @ p_u)
        x_vec, _, out = self._vecs
        x_vec.setArray(np.ascontiguousarray(p_x))
        self.shell.fine_matrix.mult(x_vec, out)
        shell = out.getArray(readonly=True) + s
        b_s = np.empty(p_u.size)
        self.comm.Allreduce(np.ascontiguousarray(self.b_rows_t @ s), b_s, op=MPI.SUM)
        body = self._ev.blocks[1] @ p_u + self._tau * p_u - b_s
        return np.concatenate([shell, body])

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """Return ``S r``: a distributed shell V-cycle, the body block solved on every rank."""
        return np.concatenate([self.shell.precondition(r[:self.m]), self.body.solve(r[self.m:])])

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        """Return ``a . b``: the shell rows summed over ranks, plus the body rows."""
        shell = self.comm.allreduce(float(a[:self.m] @ b[:self.m]), op=MPI.SUM)
        return float(shell + a[self.m:] @ b[self.m:])

    def _local(self, full: np.ndarray) -> np.ndarray:
        """Return this rank's shell dofs of a full vector, then its body dofs."""
        return np.concatenate([full[:self.n][self.owned], full[self.n:]])

    def _full(self, local: np.ndarray) -> np.ndarray:
        """Return the full vector (the shell rows allgathered), the same on every rank."""
        return np.concatenate([self.split.allgather_owned(local[:self.m]), local[self.m:]])


def split_joint_system(split: SplitNewtonSolver, joint: CoupledEnergy,
                       prolongations: tuple[sp.csr_matrix, ...],
                       options: MultigridOptions) -> tuple[SplitCoupledEnergy, SplitJointKrylov]:
    """Return the joint energy and CG of ``joint`` on the split shell solver's ownership.

    The shell block's multigrid is ``split``'s own when it has no phase space (the split
    solver itself is not run by the joint step), else one built on its energy and layout with
    ``options`` without the phase space; ``joint.shell.penalty_factor`` is ``G``, the same on
    every rank.
    """
    energy = SplitCoupledEnergy(split.energy, joint)
    own = split.linear
    shell = (own if isinstance(own, SplitMultigridSystem) and own.phase is None else
             SplitMultigridSystem(split.energy, prolongations, joint.shell.penalty_factor,
                                  split.layout.cluster_rank, replace(options, phase_space=False)))
    return energy, SplitJointKrylov(shell, energy)


__all__ = ["JointRows", "SplitCoupledEnergy", "SplitJointKrylov", "split_joint_system"]
