"""The wrinkle-phase coarse space over the split layout (:mod:`solvers.phase_space`, distributed).

The basis is the serial one: with ``d = x - y``, ``D_k`` the surface gradients and ``(u_j, v_j)``
the tangent frame of coarse hat ``phi_j``, the columns of Z are

    Z[3 v + c, 3 j + m] = phi_j(v) t_m[v, c] / ||column||,   t_0 = d, t_{1,2} = (u_j, v_j) . D d,

and the correction is ``Q r = Z A_Z^{-1} Z^T r`` with ``A_Z = Z^T (A + tau I + G^T G) Z``,
used by the deflation preconditioner A-DEF2 (Tang, Nabben, Vuik & Erlangga, J. Sci. Comput.
39, 2009) around the V-cycle. Distributed:

* Z is a ``MATMPIAIJ`` whose rows are the fine dofs of each rank (PETSc numbering of
  :class:`~.split_multigrid.LevelNumbering`) and whose columns are numbered by the owner of
  each hat (3 per hat); its values are computed from the full x on every rank (the column
  norms need all rows) and each rank sets its rows;
* ``Z^T (A Z)`` and ``(G Z)^T (G Z)`` are parallel products (symbolic parts reused); ``A_Z``
  is small (3 columns per coarse hat) and is gathered to every rank and factorised there by
  the serial LDL^T, whose inertia says whether A is indefinite (as in the serial space);
* ``Q r``: ``Z^T r`` gathered to every rank, the small solve, ``Z`` times the owned part.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from models.backend import PETSc
from solvers.linear import FactorReport, LinearSolverOptions, SparseDirectSolver
from solvers.phase_space import TEST_FIELDS, hat_frames, surface_gradients, z_values


def _gathered(mat: Any, comm: Any) -> sp.csr_matrix:
    """Every rank's rows of a distributed AIJ ``mat`` as one scipy CSR on every rank."""
    indptr, indices, data = mat.getValuesCSR()
    parts = comm.allgather((np.diff(indptr), indices, data))
    counts = np.concatenate([p[0] for p in parts])
    return sp.csr_matrix((np.concatenate([p[2] for p in parts]),
                          np.concatenate([p[1] for p in parts]),
                          np.concatenate([[0], np.cumsum(counts)])), shape=mat.getSize())


class SplitPhaseSpace:
    """Z over the ranks, the gathered ``A_Z`` and the correction ``Q r`` (module docstring).

    Args:
        vertices: Rest positions of the shell ``(n, 3)`` (the same on every rank).
        faces: Shell triangles.
        hats: Vertex hats ``(n, n_c)`` (:func:`solvers.phase_space.hat_matrix`).
        fine: ``(dof, owned, sizes)`` of the fine level: (3n,) PETSc index of every dof,
            (3 n_r,) this rank's dofs in row order, (local, global) rows.
        columns: ``(dof, sizes)``: (3 n_c,) PETSc index of every column ``3 j + m`` and
            (local, global) columns.
        comm: Communicator.

    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, hats: sp.csr_matrix,
                 fine: tuple[np.ndarray, np.ndarray, tuple[int, int]],
                 columns: tuple[np.ndarray, tuple[int, int]], comm: Any) -> None:
        fine_dof, fine_owned, fine_sizes = fine
        hat_dof, hat_sizes = columns
        self.comm = comm
        self.gradients = surface_gradients(vertices, faces)
        self.rest = np.asarray(vertices, dtype=np.float64)
        self.frames = hat_frames(vertices, faces, hats)
        coo = hats.tocoo()
        v, j = np.repeat(coo.row, 3 * TEST_FIELDS), np.repeat(coo.col, 3 * TEST_FIELDS)
        c = np.tile(np.repeat(np.arange(3), TEST_FIELDS), coo.nnz)
        m = np.tile(np.arange(TEST_FIELDS), 3 * coo.nnz)
        self.vertex, self.component, self.field, self.hat = v, c, m, j
        self.hat_value = np.repeat(coo.data, 3 * TEST_FIELDS)
        self.column = TEST_FIELDS * j + m
        self.n_columns = TEST_FIELDS * hats.shape[1]
        self.values = np.zeros(v.size)
        owned = np.zeros(fine_dof.size, dtype=bool)
        owned[fine_owned] = True
        self.mine = np.flatnonzero(owned[3 * v + c])
        z: Any = PETSc.Mat().create(comm=comm)
        z.setSizes((fine_sizes, hat_sizes))
        z.setType(PETSc.Mat.Type.AIJ)
        z.setPreallocationCOO(fine_dof[3 * v + c][self.mine].astype(PETSc.IntType),
                              hat_dof[self.column][self.mine].astype(PETSc.IntType))
        self.z = z
        self._az: Any = None
        self._galerkin: Any = None
        self._gz: Any = None
        self._gtg: Any = None
        self._gram: Any = None
        self._base: tuple[sp.csr_matrix, float] | None = None
        self._solver: SparseDirectSolver | None = None
        self._rhs, self._solution = z.createVecRight(), z.createVecRight()
        self._scatter, self._full = PETSc.Scatter.toAll(self._rhs)
        self._range = self._rhs.getOwnershipRange()

    def set_fields(self, x: np.ndarray, target: np.ndarray) -> None:
        """Z's values from the positions x and the penalty target y (both ``(n, 3)``)."""
        d = np.asarray(x, dtype=np.float64).reshape(-1, 3) - target
        grads = np.stack([g @ d for g in self.gradients], axis=-1)
        z_values(self.values, self.hat_value, self.vertex, self.component, self.field,
                 self.hat, self.frames, d, grads)
        norms = np.bincount(self.column, self.values ** 2, self.n_columns)
        scale = np.where(norms > 0, 1.0 / np.sqrt(np.where(norms > 0, norms, 1.0)), 0.0)
        self.values *= scale[self.column]
        self.z.setValuesCOO(np.ascontiguousarray(self.values[self.mine],
                                                 dtype=PETSc.ScalarType))
        self._base = None

    def update(self, fine: Any, g: Any, tau: float = 0.0,
               shift_only: bool = False) -> FactorReport:
        """Factorise the gathered ``Z^T (A + tau I + G^T G) Z`` (collective).

        Args:
            fine: The distributed fine matrix, shift included.
            g: The distributed penalty factor G (None without penalty).
            tau: The shift in ``fine``.
            shift_only: Same fields and matrix as the last full update up to the shift:
                ``Z^T A Z + (tau - tau_last) Z^T Z`` without the fine products.

        Returns:
            The LDL^T report (``usable_spd`` False: do not use the correction).

        """
        if shift_only and self._base is not None:
            base, base_tau = self._base
            total = (base + (tau - base_tau) * self._gram_matrix()).tocsr()
        else:
            total = self._galerkin_matrix(fine)
            if g is not None:
                total = (total + self._penalty_part(g)).tocsr()
            self._base = (total, tau)
        diagonal = total.diagonal()
        total = (total + sp.diags(np.where(diagonal > 0, 0.0, 1.0))).tocsr()
        total.sort_indices()
        if self._solver is None or self._solver.pattern.nnz != total.nnz:
            self._solver = SparseDirectSolver(total, LinearSolverOptions(symmetric="ldlt"))
        return self._solver.factorize(total)

    def _galerkin_matrix(self, fine: Any) -> sp.csr_matrix:
        """``Z^T (A Z)``, gathered (parallel products, symbolic parts reused)."""
        if self._az is None:
            self._az = fine.matMult(self.z)
            self._galerkin = self.z.transposeMatMult(self._az)
        else:
            fine.matMult(self.z, result=self._az)
            self.z.transposeMatMult(self._az, result=self._galerkin)
        return _gathered(self._galerkin, self.comm)

    def _penalty_part(self, g: Any) -> sp.csr_matrix:
        """``(G Z)^T (G Z)``, gathered."""
        if self._gz is None:
            self._gz = g.matMult(self.z)
            self._gtg = self._gz.transposeMatMult(self._gz)
        else:
            g.matMult(self.z, result=self._gz)
            self._gz.transposeMatMult(self._gz, result=self._gtg)
        return _gathered(self._gtg, self.comm)

    def _gram_matrix(self) -> sp.csr_matrix:
        """``Z^T Z`` of the current fields, gathered."""
        self._gram = (self.z.transposeMatMult(self.z) if self._gram is None
                      else self.z.transposeMatMult(self.z, result=self._gram))
        return _gathered(self._gram, self.comm)

    def correct(self, r: Any, out: Any) -> None:
        """``out = Z A_Z^{-1} Z^T r`` (collective)."""
        assert self._solver is not None  # update() ran first (internal invariant)
        self.z.multTranspose(r, self._rhs)
        self._scatter.scatter(self._rhs, self._full)  # insert, forward
        solution = self._solver.solve(self._full.getArray(readonly=True))
        self._solution.setArray(solution[self._range[0]: self._range[1]])
        self.z.mult(self._solution, out)


__all__ = ["SplitPhaseSpace"]
