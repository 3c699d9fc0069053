"""The composite shell energy W = k_L W_L + k_A W_A + k_B W_B + k_P W_P + k_F W_F.

* ``W_L = sum_e (l_e - l0_e)^2 / l0_e`` edge membrane (:mod:`models.shell.membrane`),
* ``W_A = sum_T (A_T - A0_T)^2 / A0_T`` area membrane (optional, ``k_A = 0`` switches it off),
* ``W_B = sum_h w_h [(theta_h - theta0_h)^2 + c b(pi - |theta_h|)]`` hinge bending with its fold
  contact ``c = fold_contact`` (:mod:`models.shell.bending`), each ``theta_h`` on the branch
  nearest to its reference angle once :meth:`follow_hinges` set one,
* ``W_P = ||H (x - y)||^2`` cluster penalty to the embedded target y (:mod:`models.shell.penalty`),
* ``W_F = sum_T w_T b(s_T)`` flip barrier (:mod:`models.shell.barrier`, ours, not in the draft)
  over the faces of rest quality below ``flip_quality`` (by default every face):
  zero while such a face keeps ``s_T = n_T . r_T / (2 A0_T) >= flip_activation`` and +inf at
  ``s_T <= 0``, so it never collapses or turns over. The reference normals ``r_T`` are the unit
  normals of the faces on the penalty target y (the rest normals until :meth:`set_target`), so
  the barrier follows the body's rotations.

The terms of Remillard & Kry 2013 are the first four.

A term whose stiffness is 0 is skipped entirely (no kernel call, no stencils in the pattern).
:meth:`ShellEnergy.evaluate` returns the value, the flat gradient and the Hessian assembled
into one fixed CSR pattern (the same ``indptr``/``indices`` arrays on every call, see
:mod:`models.shell.assembly`). The constant penalty Hessian ``2 k_P (H^T H) kron I3`` is either
merged into that pattern once ("assembled") or returned as the factor ``G`` with
``G^T G = 2 k_P (H^T H) kron I3`` ("low_rank") for the augmented solve
``[[A, G^T], [G, -I]]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal, Protocol

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError
from models.shell.assembly import (
    HessianMode,
    HessianSink,
    ScatterMap,
    StencilPattern,
    TermEval,
    assemble,
    check_hessian_mode,
    check_order,
)
from models.shell.barrier import (
    barrier_weights,
    check_activation,
    flip_barrier,
    reference_normals,
)
from models.shell.bending import bending_energy_density, check_contact, hinge_bending
from models.shell.dofs import check_positions
from models.shell.hinge_angle import hinge_angles, on_branch
from models.shell.membrane import area_membrane, edge_membrane
from models.shell.penalty import PenaltyOperator, penalty_factor, penalty_gram, penalty_term
from models.shell.rest import RestState, face_quality
from models.shell.schedule import StencilSchedule, check_threads, vertex_parts
from models.shell.topology import ShellTopology

PenaltyHessian = Literal["assembled", "low_rank"]


class Kernel(Protocol):
    """A stencil term's kernel: ``kernel(x, stencils, order=, hessian_mode=, ...) -> TermEval``.

    Pure in the positions: the rest state and the stiffness are bound when the term is made
    (:class:`StencilTerm`); ``sink`` and ``schedule`` are passed to fused kernels only.
    """

    def __call__(self, x: np.ndarray, stencils: np.ndarray, *, order: int,
                 hessian_mode: HessianMode, **fused: Any) -> TermEval:
        """Value, gradient and local Hessian blocks (or blocks added into ``sink``)."""


@dataclass(frozen=True)
class StencilTerm:
    """One local term of the composite energy: a kernel over a fixed stencil array.

    Every local term is evaluated, patterned and assembled the same way by
    :class:`ShellEnergy`, which is a loop over its terms: a new energy term is a pure kernel
    (value, gradient, local Hessian blocks of each stencil) and one more ``StencilTerm``.

    Attributes:
        name: key of the term in :attr:`ShellEval.terms` and ``elements``.
        stencils: ``(m, k)`` int64 vertex indices of the m stencils.
        kernel: the term's kernel with its rest data and stiffness bound.
        fused: the kernel accepts ``sink`` (blocks added straight into the CSR data) and
            ``schedule`` (race-free threads); otherwise it returns its blocks.

    """

    name: str
    stencils: np.ndarray
    kernel: Kernel
    fused: bool = True

    def evaluate(self, x: np.ndarray, order: int, mode: HessianMode,
                 sink: HessianSink | None, schedule: StencilSchedule | None) -> TermEval:
        """Evaluate the term (its stiffness included)."""
        fused = {"sink": sink, "schedule": schedule} if self.fused else {}
        return self.kernel(x, self.stencils, order=order, hessian_mode=mode, **fused)
"""The terms whose kernels take a :class:`~models.shell.schedule.StencilSchedule` (the area
membrane runs serially)."""


@dataclass(frozen=True)
class ShellParams:
    """Stiffnesses and Hessian options of the shell energy.

    Defaults follow the author's public code (jiongchen/bigbang, test_emb_thin_shell.cc):
    edge 1e3, bending 1e-1, penalty 1e3; the area term is off. Physical values come from
    :mod:`models.shell.stiffness`. The flip barrier is on for every face (``k_F = 1e3``,
    active below ``s = 0.1``); it is exactly zero unless a face shrinks / tilts to a tenth of
    its rest area projected on its reference normal. It lets accepted rest slivers converge
    and keeps regular faces from folding too (docs/notes/flip-barrier.md).
    ``flip_quality = 0.5`` restricts it to near-degenerate faces, ``k_F = 0`` switches it off.

    Attributes:
        k_L: Edge membrane stiffness (energy / length; >= 0, 0 = off).
        k_A: Area membrane stiffness (energy / area; >= 0, 0 = off).
        k_B: Bending stiffness (energy; >= 0, 0 = off).
        k_P: Penalty stiffness (energy / length^2; >= 0, 0 = off; needs H).
        k_F: Flip barrier stiffness (energy / area; >= 0, 0 = off; :mod:`models.shell.barrier`).
        flip_activation: Ratio ``s_hat`` in (0, 1] below which the flip barrier acts
            (dimensionless; ``s = A / A0`` times the cosine of the tilt from the reference).
        flip_quality: The barrier covers the faces of rest quality ``4 sqrt(3) A / sum |e|^2``
            below this, in [0, 1] (dimensionless; 1 = every face, 0 = none).
        fold_contact: Contact of a hinge's two faces (dimensionless, 0 = off): each hinge
            also pays ``fold_contact k_B w_h b(pi - |theta_h|)``, IPC's log barrier in the gap
            to flat-on-flat (:func:`models.shell.bending.hinge_bending`), so a fold closes up
            to its faces touching, not through them (docs/notes/hinge-branches.md).
        fold_gap: The fold contact's activation gap ``d_hat`` [rad], in ``(0, pi)``: zero
            while every hinge keeps ``|theta| <= pi - fold_gap``.
        hessian_mode: "exact", "gauss_newton" or "projected" local Hessians.
        penalty_hessian: "assembled" (H^T H merged into the pattern) or "low_rank" (the factor
            G is returned instead and the assembled Hessian excludes the penalty).
        threads: Threads of the element kernels (>= 1; :mod:`models.shell.schedule`). 1
            (the default) is the plain loop; more split the stencils into bands of the mesh
            (results equal up to round-off). Keep 1 under MPI (one core per rank).

    """

    k_L: float = 1e3
    k_A: float = 0.0
    k_B: float = 1e-1
    k_P: float = 1e3
    k_F: float = 1e3
    flip_activation: float = 0.1
    flip_quality: float = 1.0
    fold_contact: float = 1.0
    fold_gap: float = 0.1
    hessian_mode: HessianMode = "exact"
    penalty_hessian: PenaltyHessian = "assembled"
    threads: int = 1

    def __post_init__(self) -> None:
        """Validate stiffnesses (finite, >= 0) and option names."""
        for name in ("k_L", "k_A", "k_B", "k_P", "k_F"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise InputError(f"{name}: must be a finite number >= 0, got {value!r}")
        check_activation(self.flip_activation)
        if not (np.isfinite(self.flip_quality) and 0.0 <= self.flip_quality <= 1.0):
            raise InputError(f"flip_quality: must be in [0, 1], got {self.flip_quality!r}")
        check_contact(self.fold_contact, self.fold_gap)
        check_hessian_mode(self.hessian_mode)
        check_threads(self.threads, "threads")
        if self.penalty_hessian not in ("assembled", "low_rank"):
            raise InputError(f"penalty_hessian: expected 'assembled' or 'low_rank', "
                             f"got {self.penalty_hessian!r}")


@dataclass(frozen=True, eq=False)
class ShellEval:
    """Result of :meth:`ShellEnergy.evaluate`.

    Attributes:
        value: Total energy W.
        grad: Flat gradient (3 n,), or None for order 0.
        hess: Hessian csr_matrix (3 n, 3 n) on the fixed pattern, or None for order < 2.
        penalty_factor: G (3 c, 3 n) when penalty_hessian == "low_rank" and order 2, else None.
        terms: Energy of each active term: keys among "membrane_edge", "membrane_area",
            "bending", "penalty", "flip_barrier" (stiffness included; the barrier is +inf when
            a face is collapsed or turned over, the bending with its fold contact when a fold
            has closed through itself).
        elements: Energy of each stencil of each active term (same keys; edges, faces,
            hinges, clusters or barrier faces in the order the energy holds them).

    """

    value: float
    grad: np.ndarray | None
    hess: sp.csr_matrix | None
    penalty_factor: sp.csr_matrix | None
    terms: dict[str, float] = field(default_factory=dict)
    elements: dict[str, np.ndarray] = field(default_factory=dict)


class ShellEnergy:
    """The composite discrete-shell energy over a fixed topology and rest state."""

    def __init__(self, topology: ShellTopology, rest: RestState, params: ShellParams,
                 H: sp.spmatrix | sp.sparray | np.ndarray | None = None) -> None:
        """Set up active terms and the constant penalty parts (the pattern: on first use).

        Args:
            topology: Shell connectivity.
            rest: Rest state of the same topology.
            params: Stiffnesses and Hessian options.
            H: (c, n) cluster matrix; required when ``params.k_P > 0``.

        Raises:
            InputError: ``k_P > 0`` without H, or H of the wrong shape.

        """
        self.topology, self.rest, self.params = topology, rest, params
        n = topology.n_vertices
        if params.k_P > 0 and H is None:
            raise InputError("H: k_P > 0 needs a cluster matrix H (or set k_P = 0)")
        self._penalty = (PenaltyOperator.from_matrix(H, n)
                         if (H is not None and params.k_P > 0) else None)
        self._target = rest.positions.copy()
        self._rest_normals = reference_normals(rest.positions, topology.faces, rest.rest_areas,
                                               np.tile([0.0, 0.0, 1.0], (topology.n_faces, 1)))
        self._ref_normals = self._rest_normals
        self._flip = flip_faces(topology, rest, params.flip_quality)
        self._flip_weights = barrier_weights(rest.positions, topology.faces[self._flip])
        self._bend_weights = params.k_B * rest.hinge_weights
        self._branch: np.ndarray | None = None
        self._terms = [term for term in self._local_terms() if term.stencils.shape[0] > 0]
        parts = vertex_parts(topology.faces, n, params.threads)
        self._schedules = {term.name: StencilSchedule.build(term.stencils, parts)
                           for term in self._terms if term.fused}
        assembled = self._penalty is not None and params.penalty_hessian == "assembled"
        self._factor = (penalty_factor(self._penalty, params.k_P)
                        if self._penalty is not None and not assembled else None)
        self._pattern: StencilPattern | None = None
        self._maps: dict[str, ScatterMap] = {}
        self._hess_base: np.ndarray | None = None

    def _local_terms(self) -> list[StencilTerm]:
        """Return the local terms with a positive stiffness, in a fixed order."""
        t, p, r = self.topology, self.params, self.rest
        k = self._flip
        terms = []
        if p.k_L > 0:
            terms.append(StencilTerm("membrane_edge", t.edges, partial(
                edge_membrane, rest_len=r.rest_lengths, stiffness=p.k_L)))
        if p.k_A > 0:
            terms.append(StencilTerm("membrane_area", t.faces, partial(
                area_membrane, rest_area=r.rest_areas, stiffness=p.k_A), fused=False))
        if p.k_B > 0:
            terms.append(StencilTerm("bending", t.hinges, partial(
                self._bend_kernel, theta0=r.rest_angles, weights=self._bend_weights)))
        if p.k_F > 0:
            terms.append(StencilTerm("flip_barrier", t.faces[k], partial(
                self._flip_kernel, rest_area=r.rest_areas[k], weight=self._flip_weights)))
        return terms

    def _bend_kernel(self, x: np.ndarray, hinges: np.ndarray, **kw: Any) -> TermEval:
        """Evaluate the hinge bending on the current angle branches (:meth:`follow_hinges`)."""
        p = self.params
        return hinge_bending(x, hinges, branch=self._branch, contact=p.fold_contact,
                             contact_gap=p.fold_gap, **kw)

    def follow_hinges(self, x: np.ndarray) -> None:
        """Make the hinge angles at ``x``, followed from the current branches, the new ones.

        Each hinge angle at ``x`` is taken on the branch nearest to its current reference
        (:func:`models.shell.hinge_angle.on_branch`; the first call takes ``(-pi, pi]``), and
        becomes the reference of the evaluations until the next call. Called with each
        solve's start, it lets a fold close past flat-on-flat (``theta`` through ``+-pi``)
        within a solve, or across frames that move a hinge by less than ``pi``, on a smooth,
        growing ``W_B`` instead of the jump of ``(-pi, pi]``, where the shell Newton stalls
        on the kink (``scenes/default.toml`` compressed beyond 15 %: docs/notes/hinge-branches.md).
        While no hinge moves by ``pi`` or more from its reference, every evaluation is bit
        for bit that without references.
        """
        theta = hinge_angles(check_positions(x, self.n_vertices), self.topology.hinges)
        self._branch = theta if self._branch is None else on_branch(theta, self._branch)

    def release_folds(self, x: np.ndarray) -> int:
        """Give every hinge closed through itself at ``x`` the branch ``(-pi, pi]``; count them.

        A hinge whose angle at ``x``, followed from its reference, has ``|theta| >= pi`` (the
        fold contact's ``+inf``) takes its principal angle at ``x`` as its new reference, so
        that it is open again on the side its faces now lie. The memory of which side a fold
        closed from is lost for those hinges only; the others keep their references. Nothing
        changes (and 0 is returned) while the fold contact is off or no reference is set.
        """
        if self._branch is None or self.params.fold_contact <= 0.0:
            return 0
        theta = hinge_angles(check_positions(x, self.n_vertices), self.topology.hinges)
        closed = np.abs(on_branch(theta, self._branch)) >= np.pi
        self._branch = np.where(closed, theta, self._branch)
        return int(np.count_nonzero(closed))

    @property
    def hinge_branch(self) -> np.ndarray | None:
        """The hinges' reference angles (Hn,) [rad] (a copy), None before any is set."""
        return None if self._branch is None else self._branch.copy()

    def set_hinge_branch(self, branch: np.ndarray | None) -> None:
        """Set the hinges' reference angles (Hn,) [rad], e.g. from a checkpoint; None: none.

        Raises:
            InputError: ``branch`` is not (Hn,) finite floats.

        """
        if branch is None:
            self._branch = None
            return
        arr = np.asarray(branch, dtype=np.float64)
        count = self.topology.hinges.shape[0]
        if arr.shape != (count,) or not np.all(np.isfinite(arr)):
            raise InputError(f"hinge branch: expected ({count},) finite angles, got shape "
                             f"{arr.shape}")
        self._branch = arr.copy()

    def _flip_kernel(self, x: np.ndarray, faces: np.ndarray, *, rest_area: np.ndarray,
                     weight: np.ndarray, **kw: Any) -> TermEval:
        """Evaluate the flip barrier with the current reference normals (they follow y)."""
        p = self.params
        return flip_barrier(x, faces, rest_area, weight, self._ref_normals[self._flip],
                            s_hat=p.flip_activation, stiffness=p.k_F, **kw)

    @property
    def pattern(self) -> StencilPattern:
        """The fixed CSR pattern of the Hessian (+ H^T H when assembled), built on first use.

        Only order-2 evaluations need it: an energy used for values and gradients alone
        (e.g. the whole shell next to a solver split over ranks) never holds it.
        """
        if self._pattern is None:
            stencils = {term.name: term.stencils for term in self._terms}
            gram = (penalty_gram(self._penalty) if self._penalty is not None
                    and self.params.penalty_hessian == "assembled" else None)
            self._pattern = StencilPattern.from_stencils(
                list(stencils.values()), self.topology.n_vertices,
                extra=[gram] if gram is not None else [])
            self._maps = dict(zip(stencils, self._pattern.maps, strict=True))
            self._hess_base = (self._pattern.extra_data(0, gram, 2.0 * self.params.k_P)
                               if gram is not None else None)
        return self._pattern

    @property
    def n_vertices(self) -> int:
        """Number of shell vertices n."""
        return self.topology.n_vertices

    @property
    def target(self) -> np.ndarray:
        """Current penalty target y (n, 3) (a copy)."""
        return self._target.copy()

    @property
    def penalty_factor(self) -> sp.csr_matrix | None:
        """G = sqrt(2 k_P) (H kron I3) in "low_rank" mode (constant), else None."""
        return self._factor

    @property
    def penalty_operator(self) -> PenaltyOperator | None:
        """The cluster matrix as a :class:`PenaltyOperator` (built once), None when k_P = 0."""
        return self._penalty

    def penalty_gram(self) -> sp.csr_matrix | None:
        """Vertex-level H^T H (n, n), or None when the penalty is off."""
        return penalty_gram(self._penalty) if self._penalty is not None else None

    def set_target(self, y: np.ndarray, normals: bool = True) -> None:
        """Set the penalty target y (n, 3), e.g. ``B (X_q + u_q)``; validated and copied.

        The flip barrier's reference normals become the unit face normals of y (a face
        degenerate on y keeps its rest normal). ``normals = False`` keeps the current ones:
        a solve in which y moves with the unknowns (:mod:`solvers.monolithic`) holds the
        barrier's reference fixed, so that W stays a function of the positions and y alone.
        """
        self._target = check_positions(y, self.n_vertices, "y").copy()
        if not normals:
            return
        self._ref_normals = reference_normals(self._target, self.topology.faces,
                                              self.rest.rest_areas, self._rest_normals)

    @property
    def reference_normals(self) -> np.ndarray:
        """Unit reference normals (F, 3) of the flip barrier, for every face (a copy)."""
        return self._ref_normals.copy()

    @property
    def flip_faces(self) -> np.ndarray:
        """Indices of the faces the flip barrier covers (rest quality < ``flip_quality``)."""
        return self._flip.copy()

    def blocked_vertices(self, x: np.ndarray) -> np.ndarray:
        """Vertices of the stencils whose barrier is ``+inf`` at ``x`` (sorted, unique).

        The faces of a covered face turned over against its reference normal (flip barrier,
        ``s <= 0``, :mod:`models.shell.barrier`) and the four vertices of each hinge closed
        through itself (fold contact, ``|theta| >= pi``); only those two terms are evaluated.
        Empty when neither is on or nothing is blocked.
        """
        xc = check_positions(x, self.n_vertices)
        barriers = ("flip_barrier", "bending") if self.params.fold_contact > 0.0 \
            else ("flip_barrier",)
        blocked = [np.zeros(0, dtype=np.int64)]
        for term in (t for t in self._terms if t.name in barriers):
            ev = term.evaluate(xc, 0, self.params.hessian_mode, None,
                               self._schedules.get(term.name))
            if np.isfinite(ev.value) or ev.element_values is None:
                continue
            blocked.append(term.stencils[~np.isfinite(ev.element_values)].ravel())
        return np.unique(np.concatenate(blocked))

    def value(self, x: np.ndarray) -> float:
        """Total energy W(x)."""
        return self.evaluate(x, order=0).value

    def _sink(self, name: str, data: np.ndarray | None) -> HessianSink | None:
        """Fused-assembly sink of term ``name`` into ``data`` (None: the term stores blocks)."""
        return None if data is None else HessianSink.for_map(self.pattern, self._maps[name], data)

    def _term_evals(self, x: np.ndarray, order: int, mode: HessianMode,
                    data: np.ndarray | None = None) -> dict[str, TermEval]:
        """Evaluate every active term (stiffness included).

        With ``data`` (order 2) the fused kernels add their blocks straight into it
        (:class:`models.shell.assembly.HessianSink`); the others return blocks.
        """
        out = {term.name: term.evaluate(x, order, mode,
                                        self._sink(term.name, data) if term.fused else None,
                                        self._schedules.get(term.name))
               for term in self._terms}
        if self._penalty is not None:
            out["penalty"] = penalty_term(x, self._target, self._penalty, order=min(order, 1),
                                          stiffness=self.params.k_P)
        return out

    def evaluate(self, x: np.ndarray, order: int = 2,
                 hessian: HessianMode | None = None) -> ShellEval:
        """Energy, gradient and Hessian at positions ``x``.

        Args:
            x: (n, 3) positions (or flat (3 n,)).
            order: 0 value, 1 + gradient, 2 + Hessian.
            hessian: Hessian mode for this call (default ``params.hessian_mode``).

        Returns:
            ShellEval (see its docstring).

        """
        check_order(order)
        mode = self.params.hessian_mode if hessian is None else hessian
        check_hessian_mode(mode, "hessian")
        xc = check_positions(x, self.n_vertices)
        data = None
        if order >= 2:
            nnz = self.pattern.nnz
            data = np.zeros(nnz) if self._hess_base is None else self._hess_base.copy()
        evals = self._term_evals(xc, order, mode, data)
        grad = None
        if order >= 1:
            grad = np.zeros(3 * self.n_vertices)
            for ev in evals.values():
                grad += ev.grad  # type: ignore[arg-type]
        hess = self._assemble(evals, data) if data is not None else None
        return ShellEval(value=float(sum(ev.value for ev in evals.values())), grad=grad,
                         hess=hess, penalty_factor=self._factor if order >= 2 else None,
                         terms={name: ev.value for name, ev in evals.items()},
                         elements={name: ev.element_values for name, ev in evals.items()
                                   if ev.element_values is not None})

    def _assemble(self, evals: dict[str, TermEval], data: np.ndarray) -> sp.csr_matrix:
        """Add the stored local blocks to ``data`` and wrap it as the Hessian.

        ``data`` already holds the constant penalty part and the blocks of the fused terms.
        """
        contributions = [(self._maps[name], evals[name].blocks) for name in self._maps
                         if evals[name].blocks is not None]
        return assemble(self.pattern, contributions, out=data)  # type: ignore[arg-type]

    def bending_density(self, x: np.ndarray) -> np.ndarray:
        """Per-vertex bending energy density k_B W_B split to edge vertices / vertex area (n,).

        Zero everywhere when k_B = 0 or there are no hinges.
        """
        xc = check_positions(x, self.n_vertices)
        if not any(term.name == "bending" for term in self._terms):
            return np.zeros(self.n_vertices)
        areas = np.where(self.rest.vertex_areas > 0, self.rest.vertex_areas, 1.0)
        return bending_energy_density(xc, self.topology.hinges, self.rest.rest_angles,
                                      self._bend_weights, areas, self._branch,
                                      self.params.fold_contact, self.params.fold_gap)


def flip_faces(topology: ShellTopology, rest: RestState, flip_quality: float) -> np.ndarray:
    """Return the faces of rest quality below ``flip_quality`` (every face when it is 1)."""
    if flip_quality >= 1.0:
        return np.arange(topology.n_faces)
    return np.flatnonzero(face_quality(rest.positions, topology.faces) < flip_quality)
