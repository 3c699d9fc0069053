"""Two-way coupling as one minimisation: body and shell in one Newton solve.

Remillard & Kry 2013 (sec. 4.4) couple skin and body both ways through the cluster penalty.
Per body (sub)step the unknowns are the shell positions ``x`` (n, 3) and the body's
displacement dofs ``u`` (n_b, 3; every rank holds all of them, in the global dof order: the
body is coarse), and the step minimises one energy

    E(x, u) = Pi(u) + W(x; y(u)),        y(u) = X_T + B u,

``Pi`` the body's incremental potential (its UFL form, :mod:`solvers.body`; inertia and contact
included) and ``W`` the shell energy whose penalty ``k_P ||H (x - y(u))||^2`` now depends on
both unknowns. With ``P = 2 k_P (H^T H) (x) I_3`` and ``f = P (x - y)`` (the penalty force,
:func:`models.coupling.penalty_force`),

    dE/dx = dW/dx,                 dE/du = dPi/du - B^T f,
    d2E   = [[K_x, -P B], [-B^T P, K_u + B^T P B]],

``K_x`` the shell Hessian (penalty included) and ``K_u`` the body's. With the penalty as the
low-rank factor ``G`` (``G^T G = P``) the coupled factor is ``[G, -G B]`` and the rest of the
Hessian is block diagonal. Pinned body dofs keep their values: their gradient entries are zero
and their rows and columns are the identity. The flip barrier's reference normals are those of
``y`` at the start of the solve and stay fixed inside it
(:meth:`models.shell.energy.ShellEnergy.set_target`), so ``E`` is a function of ``(x, u)``.

:class:`CoupledEnergy` is that energy in the interface of the shell's Newton solver, which
minimises it (:mod:`solvers.shell_newton`: shifted Newton matrices, Armijo line search on
``E``, which is ``+inf`` where ``det F <= 0`` or a face turns over). The joint system is
solved like the shell's own, by the method its size chose: factorised (MUMPS LDL^T with
inertia checks, :data:`JOINT_LINEAR`) or by CG with the shell's multigrid on the shell block
and the body block factorised (:mod:`solvers.joint_krylov`). Under MPI the body's gradient
and Hessian are gathered on every rank; the scalars every rank decides on (``Pi``) are rank
0's, so all ranks take the same steps. The shell part is then split over the ranks
(:mod:`solvers.decomposition.split_coupled`, from the size
:func:`solvers.solver_choice.choose_joint_split` names) or, for a small shell, this energy's
joint system is solved whole on every rank.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from models.backend import MPI
from models.coupling import penalty_force
from models.shell.energy import ShellEnergy
from solvers.body_newton import EnergyNewton
from solvers.linear import LinearSolverOptions

JOINT_LINEAR = LinearSolverOptions(symmetric="ldlt", matrix_format="sbaij", mumps_blr=False)
"""Factorisation of the joint augmented system: MUMPS LDL^T of the upper block triangle with
full-rank fronts (the body and cluster unknowns meet in dense fronts, where block low-rank
compression does not pay: 11 % less CPU per two-way frame, docs/notes/two-way-coupling.md)."""


def gather_vector(vec: Any, comm: MPI.Comm) -> np.ndarray:
    """Return the whole distributed PETSc vector on every rank (global order; collective)."""
    return np.concatenate(comm.allgather(np.array(vec.array_r, copy=True)))


def gather_matrix(mat: Any, comm: MPI.Comm) -> sp.csr_matrix:
    """Return the whole distributed PETSc AIJ matrix on every rank as CSR (collective).

    Every rank's owned rows (global columns, ``MatGetRowIJ`` order) are concatenated in rank
    order, so the pattern is the same on every call for a matrix of fixed pattern.
    """
    indptr, indices, data = mat.getValuesCSR()
    parts = comm.allgather((np.asarray(indptr), np.asarray(indices), np.asarray(data)))
    offsets = np.cumsum([0] + [p[0][-1] for p in parts[:-1]])
    ptr = np.concatenate([[0]] + [p[0][1:] + o for p, o in zip(parts, offsets, strict=True)])
    n = mat.getSize()
    out = sp.csr_matrix((np.concatenate([p[2] for p in parts]),
                         np.concatenate([p[1] for p in parts]), ptr), shape=n)
    out.sort_indices()
    return out


class BodyUnknowns:
    """The body's step problem seen as a function of all its dofs on every rank.

    Args:
        problem: the step's :class:`solvers.body_newton.EnergyNewton`.

    """

    def __init__(self, problem: EnergyNewton) -> None:
        self.problem = problem
        self.u = problem.u
        self.comm = self.u.function_space.mesh.comm
        self.owned = self.u.x.petsc_vec.getOwnershipRange()
        self.fixed = np.concatenate(self.comm.allgather(problem.dirichlet_rows)).astype(np.int64)

    def get(self) -> np.ndarray:
        """Return the current dofs, flat (3 n_b,) in global order (collective)."""
        return gather_vector(self.u.x.petsc_vec, self.comm)

    def set(self, values: np.ndarray) -> None:
        """Set the dofs (flat, global order) on this rank's owned entries and ghosts."""
        lo, hi = self.owned
        self.u.x.petsc_vec.array_w[:] = values[lo:hi]
        self.u.x.scatter_forward()

    def energy(self) -> float:
        """``Pi(u)`` (``+inf`` where ``det F <= 0``), rank 0's value on every rank."""
        return float(self.comm.bcast(self.problem.energy(), root=0))

    def gradient(self) -> np.ndarray:
        """``dPi/du`` flat on every rank; zero on the pinned dofs."""
        g = gather_vector(self.problem.gradient(), self.comm)
        g[self.fixed] = 0.0
        return g

    def hessian(self) -> sp.csr_matrix:
        """``d^2 Pi/du^2`` on every rank (identity rows and columns on the pinned dofs)."""
        return gather_matrix(self.problem.hessian(), self.comm)


class PatternSum:
    """Sum of CSR matrices of fixed patterns placed at block offsets, into one fixed pattern.

    The shell's direct solver reuses its symbolic analysis only for an unchanged pattern
    (:func:`solvers.linear.pattern_data`), so the joint Hessian is assembled into the union
    pattern of its pieces, built once from their first values.

    Args:
        shape: shape of the sum.
        pieces: ``(matrix, row_offset, col_offset)`` with the patterns of every later call.

    """

    def __init__(self, shape: tuple[int, int],
                 pieces: list[tuple[sp.csr_matrix, int, int]]) -> None:
        self.shape = shape
        coos = [self._placed(m, r, c) for m, r, c in pieces]
        rows = np.concatenate([c.row for c in coos])
        cols = np.concatenate([c.col for c in coos])
        union = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=shape)
        union.sum_duplicates()
        union.sort_indices()
        self.indptr, self.indices = union.indptr, union.indices
        keys = np.repeat(np.arange(shape[0], dtype=np.int64), np.diff(union.indptr)) \
            * shape[1] + union.indices
        self.maps = [np.searchsorted(keys, c.row.astype(np.int64) * shape[1] + c.col)
                     for c in coos]

    @staticmethod
    def _placed(m: sp.csr_matrix, r: int, c: int) -> sp.coo_matrix:
        """``m``'s entries in CSR order, shifted by ``(r, c)`` (explicit zeros kept)."""
        rows = np.repeat(np.arange(m.shape[0]), np.diff(m.indptr)) + r
        return sp.coo_matrix((m.data, (rows, m.indices + c)))

    def __call__(self, matrices: list[sp.csr_matrix]) -> sp.csr_matrix:
        """Return the sum of ``matrices`` (the pieces' order and patterns) in the union."""
        data = np.zeros(self.indices.size)
        for m, where in zip(matrices, self.maps, strict=True):
            data[where] += m.data  # a piece's positions are distinct: no np.add.at needed
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)


@dataclass(eq=False)
class CoupledEval:
    """Value, gradient, Hessian and penalty factor of :class:`CoupledEnergy` (order 0-2).

    ``blocks`` (order 2) are the Hessian's diagonal blocks ``(K_x, K_u)`` without the
    coupled penalty (``hess`` is their sum in one pattern, plus the assembled coupling when
    the penalty is not a factor).
    """

    value: float
    grad: np.ndarray | None
    hess: sp.csr_matrix | None
    penalty_factor: sp.csr_matrix | None
    blocks: tuple[sp.csr_matrix, sp.csr_matrix] | None = None


class CoupledEnergy:
    """``E(x, u) = Pi(u) + W(x; X_T + B u)`` over ``z = (x, u)`` stacked as (n + n_b, 3) rows.

    Args:
        shell: the shell energy (its target and reference normals are set by this object).
        rest: ``X_T`` (n, 3), the shell's rest positions (``B X_q``).
        B: (n, n_b) embedding matrix, columns in the body's global node order.
        body: the body's step problem on every rank.

    Attributes:
        embedding_free: ``B (x) I_3`` (3n x 3 n_b) with the pinned body columns zero.
        factor: ``F = [G, -G B]`` (pinned body columns zero), None without the factor G.
        body_factor: ``F``'s body columns ``-G B`` (the joint CG's body block), or None.

    """

    def __init__(self, shell: ShellEnergy, rest: np.ndarray, B: sp.csr_matrix,
                 body: BodyUnknowns) -> None:
        self.shell, self.rest, self.B, self.body = shell, np.asarray(rest), B.tocsr(), body
        self.n = shell.n_vertices
        self.n_b = B.shape[1]
        self.BT = self.B.T.tocsr()
        self.k_P = shell.params.k_P
        Bk = sp.kron(self.B, sp.identity(3), format="csr")
        free = np.ones(3 * self.n_b)
        free[body.fixed] = 0.0
        Bk_free = (Bk @ sp.diags(free)).tocsr()
        self.embedding_free = Bk_free
        self.factor = self._coupled_factor(Bk_free)
        self.body_factor = None if self.factor is None else self.factor[:, 3 * self.n:].tocsr()
        self.constant = self._coupling_blocks(Bk_free) if self.factor is None else None
        self._sum: PatternSum | None = None

    def _coupled_factor(self, Bk: sp.csr_matrix) -> sp.csr_matrix | None:
        """``[G, -G B]`` when the shell's penalty is the low-rank factor G, else None."""
        G = self.shell.penalty_factor
        return None if G is None else sp.hstack([G, -(G @ Bk)], format="csr")

    def _coupling_blocks(self, Bk: sp.csr_matrix) -> sp.csr_matrix | None:
        """``[[0, -P B], [-B^T P, B^T P B]]`` (pinned columns removed), None without penalty."""
        gram = self.shell.penalty_gram()
        if gram is None:
            return None
        P = sp.kron((2.0 * self.k_P) * gram, sp.identity(3), format="csr")
        PB = (P @ Bk).tocsr()
        return sp.bmat([[None, -PB], [-PB.T, Bk.T @ PB]], format="csr")

    @property
    def n_vertices(self) -> int:
        """Rows of ``z``: shell vertices plus body nodes."""
        return self.n + self.n_b

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(x (n, 3), u (n_b, 3))`` of a stacked ``z``."""
        z = np.asarray(z).reshape(-1, 3)
        return z[:self.n], z[self.n:]

    def target(self, u: np.ndarray) -> np.ndarray:
        """``y = X_T + B u`` (n, 3)."""
        return self.rest + self.B @ np.asarray(u).reshape(-1, 3)

    def value(self, x: np.ndarray) -> float:
        """Return ``E(z)`` at the stacked ``x = z`` (``+inf`` where inadmissible; collective)."""
        return self.evaluate(x, order=0).value

    def evaluate(self, x: np.ndarray, order: int = 2, hessian: Any = None) -> CoupledEval:
        """Return ``E``, its gradient and Hessian at the stacked ``x = z`` (collective).

        ``x`` is ``z``, (n + n_b, 3) or flat (the solver's name for its unknowns); the
        gradient is flat (3 (n + n_b),), the Hessian and factor as in the module doc.
        """
        ev, value, grad, k_u = self.evaluate_with(self.shell, x, order, hessian)
        if order < 2:
            return CoupledEval(value, grad, None, None)
        assert ev.hess is not None and k_u is not None  # order 2
        return CoupledEval(value, grad, self._hessian(ev.hess, k_u), self.factor,
                           (ev.hess, k_u))

    def evaluate_with(self, shell: Any, x: np.ndarray, order: int, hessian: Any
                      ) -> tuple[Any, float, np.ndarray | None, sp.csr_matrix | None]:
        """Return the shell's evaluation, ``E``, its flat gradient and ``K_u`` at ``x = z``.

        ``shell`` evaluates ``W`` (this energy's, or one split over the ranks,
        :mod:`solvers.decomposition.split_coupled`): its target is set to ``y(u)`` with the
        barrier's normals kept. The gradient (order >= 1) and ``K_u`` (order 2) are None
        below their order.
        """
        x, u = self.split(x)
        y = self.target(u)
        self.body.set(u.reshape(-1))
        shell.set_target(y, normals=False)
        ev = shell.evaluate(x, order=order, hessian=hessian)
        value = ev.value + self.body.energy()
        if order == 0:
            return ev, value, None, None
        op = self.shell.penalty_operator
        f = penalty_force(op, self.k_P, x, y) if op is not None else np.zeros_like(x)
        g_u = self.body.gradient() - (self.BT @ f).reshape(-1)
        g_u[self.body.fixed] = 0.0
        assert ev.grad is not None  # order >= 1
        grad = np.concatenate([ev.grad, g_u])
        return ev, value, grad, self.body.hessian() if order >= 2 else None

    def _hessian(self, K_x: sp.csr_matrix, K_u: sp.csr_matrix) -> sp.csr_matrix:
        """Return the joint Hessian in its fixed union pattern."""
        pieces = [(K_x, 0, 0), (K_u, 3 * self.n, 3 * self.n)]
        if self.constant is not None:
            pieces.append((self.constant, 0, 0))
        if self._sum is None:
            size = 3 * self.n_vertices
            self._sum = PatternSum((size, size), pieces)
        return self._sum([m for m, _, _ in pieces])


__all__ = ["JOINT_LINEAR", "BodyUnknowns", "CoupledEnergy", "CoupledEval", "PatternSum",
           "gather_matrix", "gather_vector"]
