"""CG for the joint Newton system of body and shell, preconditioned block by block.

The two-way Newton matrix of :mod:`solvers.monolithic` is, with ``F = [G, -G B]`` the coupled
penalty factor (``G^T G = 2 k_P H^T H (x) I_3``, pinned body columns removed),

    M = [[K_x, 0], [0, K_u]] + F^T F + tau I
      = [[K_x + G^T G + tau I,  -G^T G B], [-B^T G^T G,  K_u + B^T G^T G B + tau I]],

``K_x`` the shell Hessian without the penalty and ``K_u`` the body's. The body is coarse (a few
hundred to a few thousand dofs) and the shell fine. CG on ``M`` (Hestenes & Stiefel 1952)
with the block-diagonal (block-Jacobi) preconditioner

    S = diag(V_x, M_uu^{-1}),     M_uu = K_u + B^T G^T G B + tau I,

``V_x`` one V-cycle of the shell's geometric multigrid for ``K_x + G^T G + tau I``
(:class:`solvers.multigrid.MultigridLinearSystem`, symmetric: Chebyshev/Jacobi smoothing, the
coarsest level factorised) and ``M_uu`` factorised (MUMPS LDL^T, its pattern fixed, the
analysis reused; the factor kept while the block barely moves: :class:`BodyBlock`); ``S`` is
symmetric positive definite when both diagonal blocks are, so the iteration is a
preconditioned CG. A coarse correction on the span of ``[B; I]`` (shell and
body moving together, where ``F`` vanishes) was measured and does not pay
(docs/notes/two-way-coupling.md).

Indefiniteness, as the shell Newton expects from a linear solver (``usable_spd``): a
diagonal block found not positive definite (a new ``M_uu`` factor has a negative pivot)
fails the set-up; a CG curvature ``p^T M p <= 0`` or a non-positive ``r^T S r`` fails the
solve (the shell Newton then moves on to the next shift). The CG tolerance is the shell's
forcing term (:class:`solvers.multigrid.KrylovBase`), and a solution is accepted when its true
residual is within ``residual_slack`` of it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from solvers.linear import FactorReport, LinearSolverOptions, SparseDirectSolver
from solvers.monolithic import PatternSum
from solvers.multigrid import (
    KrylovBase,
    MultigridLinearSystem,
    gram_diagonal,
    shifted_product,
)

BODY_LINEAR = LinearSolverOptions(symmetric="ldlt", mumps_blr=False)
"""Factorisation of the body block: LDL^T, whose inertia says whether it is SPD."""

BODY_MAX_AGE = 8
"""Set-ups a body-block factor may serve after its own (docs/notes/two-way-coupling.md)."""

BODY_SHIFT_TOLERANCE = 0.25
"""Shift change, relative to the body block's mean diagonal, that keeps its factor."""


@dataclass(frozen=True)
class ShellBlock:
    """The shell's part of a joint evaluation, as the shell multigrid reads it.

    ``hess``: ``K_x`` (CSR) for the serial multigrid, a rank's rows of it
    (:class:`solvers.decomposition.split_newton.OwnedRows`) for the split one.
    """

    hess: Any
    penalty_factor: sp.csr_matrix | None


class BodyBlock:
    """``M_uu = K_u + F_u^T F_u + tau I`` factorised by MUMPS LDL^T, augmented on a large body.

    ``M_uu``'s penalty term couples every body node under a cluster, which fills its factor.
    A body with more dofs ``n`` than ``F_u`` has rows ``m`` is factorised instead as the
    augmented matrix

        [[K_u + tau I, F_u^T], [F_u, -I]],

    whose Schur complement onto the first block is ``M_uu`` (``M_uu^{-1} r`` is the first
    block of its solution for ``(r, 0)``): a sparser factor where ``m < n``; where ``m > n``
    (the shipped scenes' small bodies) ``M_uu`` stays assembled (:attr:`augmented`;
    measurements in docs/notes/two-way-coupling.md). The augmented form's ``m`` negative pivots are
    expected; one more means ``M_uu`` is not positive definite. The pattern is fixed at the
    first call, so MUMPS' analysis runs once.

    The factor is only the body block of the joint CG's preconditioner, so an earlier one
    serves while the block has barely changed (the CG stays exact on ``M``; only its
    iterations may grow): a new one is computed when none is valid (the first call, a failed
    CG: :meth:`invalidate`), after ``max_age`` reuses, or when the shift moved by more than
    ``shift_tolerance`` times the mean ``|diag(K_u + F_u^T F_u)|`` of the factorised block. A
    reused factor certifies nothing: the joint CG's curvature test ``p^T M p <= 0`` and the
    shell Newton's descent test then stand for the body block's inertia, as they do for the
    shell block's (docs/notes/two-way-coupling.md, "A body of thousands of dofs").

    Args:
        body_factor: ``F_u = -G B`` (pinned columns zero), or None without penalty.
        max_age: Set-ups a factor may serve after its own (0: factorise every set-up).
        shift_tolerance: Largest shift change, relative to the block's mean diagonal, that
            keeps a factor.
        augmented: The form: None chooses augmented when ``m < n``; without a penalty
            factor the block is assembled.

    """

    def __init__(self, body_factor: sp.csr_matrix | None, max_age: int = BODY_MAX_AGE,
                 shift_tolerance: float = BODY_SHIFT_TOLERANCE,
                 augmented: bool | None = None) -> None:
        self._factor = None if body_factor is None else sp.csr_matrix(body_factor)
        by_size = self._factor is not None and self._factor.shape[0] < self._factor.shape[1]
        self.augmented = self._factor is not None and (by_size if augmented is None
                                                       else augmented)
        self._penalty_diagonal = 0.0 if self._factor is None else gram_diagonal(self._factor)
        self._sum: PatternSum | None = None
        self._constant: list[tuple[sp.csr_matrix, int, int]] | None = None
        self._solver: SparseDirectSolver | None = None
        self.n = 0
        self.max_age, self.shift_tolerance = max_age, shift_tolerance
        self._factored: tuple[float, float] | None = None  # (tau, mean |diag|) of the factor
        self._age = 0
        self.factorizations = 0
        self.reuses = 0

    def factorize(self, k_u: sp.csr_matrix, tau: float) -> FactorReport:
        """Factorise ``M_uu`` for ``K_u`` and ``tau``, or keep the valid factor if close.

        ``usable_spd`` says whether the new factor is SPD; a kept one reports success.
        """
        if self._factored is not None and self._age < self.max_age:
            factored_tau, scale = self._factored
            if abs(tau - factored_tau) <= self.shift_tolerance * scale:
                self._age += 1
                self.reuses += 1
                return FactorReport(success=True, reason="reused", shift=float(tau))
        k_u = sp.csr_matrix(k_u)
        self.n = n = k_u.shape[0]
        m = self._factor.shape[0] if self._factor is not None and self.augmented else 0
        if self._constant is None:  # the identity (for tau), then [[., F^T], [F, -I]] or P
            self._constant = [(sp.identity(n, format="csr"), 0, 0)]
            if self.augmented:
                assert self._factor is not None  # augmented only with a factor (invariant)
                self._constant += [(self._factor.T.tocsr(), 0, n), (self._factor, n, 0),
                                   (-sp.identity(m, format="csr"), n, n)]
            elif self._factor is not None:
                self._constant += [((self._factor.T @ self._factor).tocsr(), 0, 0)]
            self._sum = PatternSum((n + m, n + m), [(k_u, 0, 0), *self._constant])
        assert self._sum is not None  # built with the constant pieces (internal invariant)
        eye, *rest = (piece for piece, _, _ in self._constant)
        matrix = self._sum([k_u, float(tau) * eye, *rest])
        if self._solver is None:
            self._solver = SparseDirectSolver(matrix, BODY_LINEAR, expected_negative=m)
        self.factorizations += 1
        report = replace(self._solver.factorize(matrix), shift=float(tau))
        self._age = 0
        scale = float(np.mean(np.abs(k_u.diagonal() + self._penalty_diagonal)))
        self._factored = (float(tau), scale) if report.usable_spd else None
        return report

    def invalidate(self) -> None:
        """Make the next :meth:`factorize` compute a new factor (after a failed CG)."""
        self._factored = None

    def solve(self, r: np.ndarray) -> np.ndarray:
        """Return ``M_uu^{-1} r`` (augmented: the first block of the solve for ``(r, 0)``)."""
        assert self._solver is not None  # factorize() ran first (internal invariant)
        if not self.augmented:
            return self._solver.solve(r)
        rhs = np.zeros(self._solver.n)
        rhs[:self.n] = r
        return self._solver.solve(rhs)[:self.n]


class JointCG(KrylovBase):
    """Preconditioned CG on the joint matrix ``M`` with ``S = diag(V_x, M_uu^{-1})``.

    The Newton-system interface of the shell Newton (``factorize(ev, tau)``, ``solve(b)``,
    ``times()``) for a joint evaluation whose ``blocks`` are ``(K_x, K_u)``
    (:class:`solvers.monolithic.CoupledEval`). A subclass holds the shell block and its
    vectors: :meth:`_shell_setup`, :meth:`apply`, :meth:`precondition`, :meth:`dot` and the
    maps :meth:`_local` / :meth:`_full` between the Newton's full vectors and the CG's. The
    CG leaves ``negative_curvature`` False: a failed CG with stale Chebyshev bounds is
    always repeated with new ones (docs/notes/multigrid.md, "Repeating a failed CG").

    Args:
        shell: The shell block's multigrid (serial or split over the ranks), without the
            phase space; its options (forcing, CG iterations, residual slack) are the CG's.
        body_factor: ``F_u = -G B`` (pinned columns zero), the body columns of ``F``.

    """

    def __init__(self, shell: Any, body_factor: sp.csr_matrix | None) -> None:
        super().__init__(shell.options)
        self.shell = shell
        self.body = BodyBlock(body_factor)
        self._ev: Any = None  # the set-up's joint evaluation
        self._tau: float | None = None

    def factorize(self, ev: Any, tau: float) -> FactorReport:
        """Set up both diagonal blocks of ``M`` for ``ev`` and shift ``tau``.

        Fails (``usable_spd`` False) when a diagonal block is not positive definite: then
        ``M`` is not (a principal submatrix of an SPD matrix is SPD).
        """
        start = time.perf_counter()
        k_x, k_u = ev.blocks
        self._tau = None
        report = self._shell_setup(k_x, tau)
        if not report.usable_spd:
            return self._setup_done(start, report)
        body = self.body.factorize(k_u, tau)
        if not body.usable_spd:
            return self._setup_done(start, replace(
                body, success=False, reason="body block not positive definite"))
        self._ev, self._tau = ev, float(tau)
        return self._setup_done(start, FactorReport(success=True, shift=float(tau)))

    def _shell_setup(self, k_x: Any, tau: float) -> FactorReport:
        """Set the shell block's multigrid up for ``K_x + G^T G + tau I`` (subclass)."""
        raise NotImplementedError

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        """Inner product of two CG vectors (subclass: reduced over ranks when split)."""
        raise NotImplementedError

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """Return ``S r`` of a CG vector (subclass)."""
        raise NotImplementedError

    def _local(self, full: np.ndarray) -> np.ndarray:
        """Return the CG vector of a full (3 (n + n_b),) Newton vector (subclass)."""
        raise NotImplementedError

    def _full(self, local: np.ndarray) -> np.ndarray:
        """Return the full Newton vector of a CG vector, the same on every rank (subclass)."""
        raise NotImplementedError

    def _accepted_cg(self, rhs: np.ndarray) -> np.ndarray | None:
        """PCG from zero; the solution if it converged to a true residual within the slack."""
        if self._tau is None:
            return None
        b = self._local(rhs)
        x, its, converged = self._cg(b)
        self.stats.iterations.append(its)
        residual = self._residual(x, b) if converged else np.inf
        if residual > self.options.residual_slack * self.eta:
            self.body.invalidate()  # the retry (or the next shift) factorises anew
            return None
        self.stats.true_residuals.append(residual)
        return self._full(x)

    def _residual(self, x: np.ndarray, b: np.ndarray) -> float:
        """``||b - M x|| / ||b||`` of CG vectors."""
        r = b - self.apply(x)
        return math.sqrt(self.dot(r, r)) / (math.sqrt(self.dot(b, b)) or 1.0)

    def _cg(self, rhs: np.ndarray) -> tuple[np.ndarray, int, bool]:
        """``(x, iterations, converged)`` of preconditioned CG to ``||r|| <= eta ||b||``."""
        x = np.zeros_like(rhs)
        r = np.array(rhs, dtype=np.float64)
        stop = self.eta * math.sqrt(self.dot(r, r))
        if stop == 0.0:
            return x, 0, True
        z = self.precondition(r)
        rz = self.dot(r, z)
        p = z.copy()
        for k in range(1, self.options.max_iterations + 1):
            if not rz > 0.0:  # S not positive definite on r
                return x, k, False
            q = self.apply(p)
            curvature = self.dot(p, q)
            if not curvature > 0.0:  # negative curvature: M is not SPD
                return x, k, False
            alpha = rz / curvature
            x += alpha * p
            r -= alpha * q
            if math.sqrt(self.dot(r, r)) <= stop:
                return x, k, True
            z = self.precondition(r)
            rz, rz_old = self.dot(r, z), rz
            p = z + (rz / rz_old) * p
        return x, self.options.max_iterations, False

    def _failed(self, rhs: np.ndarray) -> np.ndarray:
        """Return a failed direction (NaN): the shell Newton moves on to the next shift."""
        return np.full(rhs.shape, np.nan)

    def renew_bounds(self) -> None:
        """Make the shell multigrid's Chebyshev smoothers re-estimate their bounds."""
        self.shell.renew_bounds()
        self._bounds_stale = False

    def reset_forcing(self) -> None:
        """Start a new Newton solve (forcing history; the shell smoothers' bounds)."""
        super().reset_forcing()
        self.shell.reset_forcing()

    def times(self) -> tuple[float, float, float]:
        """Return (set-up, analysis, CG solve) seconds."""
        return (self.stats.setup_time, 0.0, self.stats.solve_time)


class JointKrylovSystem(JointCG):
    """Block-preconditioned CG for the joint body-shell Newton matrix (serial, every rank).

    Args:
        shell: The shell's multigrid (its hierarchy ends at the shell's ``3 n`` dofs); its
            options (forcing, CG iterations, residual slack) are this solver's too.
        shell_factor: The shell's penalty factor ``G`` (None without penalty).
        body_factor: ``F_u = -G B`` (pinned columns zero), the body columns of ``F``.

    """

    def __init__(self, shell: MultigridLinearSystem, shell_factor: sp.csr_matrix | None,
                 body_factor: sp.csr_matrix | None) -> None:
        if shell.phase is not None:
            raise InputError("JointKrylovSystem: the shell multigrid must run without the "
                             "phase space (its V-cycle is the shell block's preconditioner)")
        super().__init__(shell, body_factor)
        self.n = shell.n
        self.shell_factor = shell_factor

    def _shell_setup(self, k_x: Any, tau: float) -> FactorReport:
        """Set the shell multigrid up for ``K_x + G^T G + tau I``."""
        if k_x.shape[0] != self.n:
            raise InputError(f"JointKrylovSystem: shell block of {k_x.shape[0]} dofs, the "
                             f"multigrid has {self.n}")
        return self.shell.factorize(ShellBlock(k_x, self.shell_factor), tau)

    def apply(self, v: np.ndarray) -> np.ndarray:
        """Return ``M v`` of the current system."""
        assert self._tau is not None  # factorize() succeeded first (internal invariant)
        return shifted_product(self._ev, self._tau, v)

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """Return ``S r``: a shell V-cycle on the shell rows, the body block solved exactly."""
        return np.concatenate([self.shell.precondition(r[:self.n]), self.body.solve(r[self.n:])])

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        """Return ``a . b``."""
        return float(a @ b)

    def _local(self, full: np.ndarray) -> np.ndarray:
        """Return the full vector itself (serial: the CG runs on full vectors)."""
        return np.asarray(full, dtype=np.float64)

    def _full(self, local: np.ndarray) -> np.ndarray:
        """Return the CG vector itself."""
        return local


__all__ = ["BodyBlock", "JointCG", "JointKrylovSystem", "ShellBlock"]
