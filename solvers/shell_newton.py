"""Newton / SQP minimisation of the shell energy W(x) with a backtracking Armijo line search.

Per frame the shell solves ``min_x W(x)`` (MISSION.md section 6, Remillard & Kry 2013 solve it
with Newton's method warm-started from the previous frame). Iteration k:

1. evaluate ``W``, ``g = grad W`` and the Hessian ``A`` (exact, Gauss-Newton or projected, see
   :mod:`models.shell.assembly`) at ``x_k``; stop when ``||g|| <= atol + rtol g_ref``, with
   ``g_ref`` the initial gradient norm or a given scale;
2. factorise ``A`` (or ``A + tau I``) with the sparse direct solver, whose symbolic analysis
   is reused between iterations and frames; when the penalty comes as the low-rank factor
   ``G`` (``G^T G = 2 k_P H^T H (x) I_3``) solve the augmented system
   ``[[A, G^T], [G, -I]] [dx; mu] = [-g; 0]`` instead;
3. if the factorisation fails, reports negative pivots (A not SPD), the direction is not a
   descent direction (``g . dx >= 0``) or the line search fails, retry with ``A + tau I``,
   ``tau = tau_0 mean|diag A|`` growing x10 (Nocedal & Wright, Numerical Optimization,
   2nd ed., Alg. 3.3), one schedule for every caller (:func:`solvers.linear.shift_candidates`):
   far from the minimum (``||g|| > switch_rtol g_ref``) an iteration after a shifted one
   starts at ``tau_prev / shift_decay`` without the unshifted attempt; nearer, ``tau = 0`` is
   tried first; a solve's first iteration starts where the previous solve's first iteration
   needed its shift, one ladder rung lower (measured schedules: docs/notes/shift-schedule.md);
   with ``linear_method = "multigrid"`` the Newton system is solved by CG preconditioned by
   geometric multigrid on the subdivision hierarchy (:mod:`solvers.multigrid`), and with
   ``modified.enabled`` one factorisation serves several iterations and frames;
4. backtracking line search: largest ``alpha = shrink^j`` with the Armijo condition
   ``W(x + alpha dx) <= W(x) + c1 alpha g . dx`` (plus a 16 eps |W| round-off allowance, so
   the final quadratically convergent steps are not rejected for noise in W);
5. stagnation stop: when ``stagnation_iterations`` accepted steps in a row neither lowered W by
   more than that round-off allowance nor reached a new smallest ``||g||``, the solve stops with
   :class:`ShellSolveError` naming the worst stencil (the vertex of largest ``|g_i|`` and its
   incident face of lowest rest quality): a sliver collapsed onto its singular zero-area state
   otherwise spins to ``max_iterations`` (docs/notes/flip-barrier.md).

Near a nondegenerate minimum the unshifted Newton step is taken with alpha = 1 and the
gradient norm converges quadratically, ``||g_{k+1}|| <= C ||g_k||^2``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import scipy.sparse as sp

from meshes.errors import InputError, SolverError
from models.shell.assembly import HESSIAN_MODES
from models.shell.hinge_angle import hinge_angles
from models.shell.rest import face_quality
from solvers.inertia_shift import OUTLIER, restart_ladder
from solvers.linear import (
    AugmentedPenaltySolver,
    DiagonalScale,
    FactorReport,
    LinearSolverOptions,
    ShiftOptions,
    SparseDirectSolver,
    factorize_with_shift,
)
from solvers.multigrid import (
    KrylovBase,
    KrylovSystem,
    MultigridLinearSystem,
    MultigridOptions,
    NewtonSystem,
    ShellHierarchy,
    shifted_product,
)

LINEAR_METHODS: tuple[str, ...] = ("direct", "multigrid")

ROUNDOFF_FACTOR: float = 16.0
"""Round-off allowance of W, in units of ``eps |W|`` (line search and stagnation test)."""


class EnergyEval(Protocol):
    """What :func:`minimize` reads from an energy evaluation (``models.shell.energy.ShellEval``)."""

    value: float
    grad: np.ndarray | None
    hess: sp.csr_matrix | None
    penalty_factor: sp.csr_matrix | None


class ShellEnergyLike(Protocol):
    """The energy interface :func:`minimize` needs (``models.shell.energy.ShellEnergy``)."""

    @property
    def n_vertices(self) -> int:
        """Number of vertices n (the unknowns are (n, 3) positions)."""

    def evaluate(self, x: np.ndarray, order: int = 2, hessian=None) -> EnergyEval:  # noqa: ANN001
        """Value, gradient (3n,) and Hessian (fixed-pattern CSR) at x."""

    def value(self, x: np.ndarray) -> float:
        """Energy W(x) only."""


@dataclass(frozen=True)
class ModifiedNewtonOptions:
    """Reuse of one factorisation across Newton iterations and frames (modified Newton).

    The step ``dx = -(A_j + tau_j I)^{-1} g_k`` with the matrix of an earlier iteration j is
    still a descent direction (that matrix is SPD) and converges linearly near the minimum
    (Kelley, Iterative Methods for Optimization, SIAM 1999, sec. 2.3 "the chord method");
    each reused iteration saves a factorisation.

    Attributes:
        enabled: Reuse the last factorisation while it keeps working (False = Newton).
        max_age: Newton iterations one factorisation may serve, counting the one that computed
            it, over consecutive frames (>= 1; 1 = Newton).
        refresh_ratio: Refactorise at the next iteration when the gradient decrease ratio
            ``||g_{k+1}|| / ||g_k||`` of a reused step exceeds this (in (0, 1]).

    """

    enabled: bool = False
    max_age: int = 4
    refresh_ratio: float = 0.5

    def __post_init__(self) -> None:
        if self.max_age < 1:
            raise InputError(f"ModifiedNewtonOptions.max_age: must be >= 1, got {self.max_age!r}")
        if not 0 < self.refresh_ratio <= 1:
            raise InputError(f"ModifiedNewtonOptions.refresh_ratio: must be in (0, 1], got "
                             f"{self.refresh_ratio!r}")


@dataclass(frozen=True)
class ShellNewtonOptions:
    """Options of the shell Newton / SQP solver.

    Attributes:
        rtol: Relative gradient tolerance: converged when ``||g|| <= atol + rtol g_ref``.
        atol: Absolute gradient tolerance (energy / length).
        gradient_scale: ``g_ref`` (energy / length); 0 uses the initial gradient norm (a
            warm-started frame passes a fixed one, else a good start is over-tightened).
        max_iterations: Newton iterations before returning unconverged (best state kept).
        hessian: Hessian mode "exact" | "gauss_newton" | "projected"; "" uses the energy's own
            ``hessian_mode``.
        far_hessian: Optional PSD mode ("gauss_newton" | "projected") used while
            ``||g|| > switch_rtol g_ref``, then ``hessian``; "" = always ``hessian``.
        switch_rtol: Relative gradient norm below which ``far_hessian`` hands over and the
            unshifted Hessian is always tried first.
        linear: Sparse direct solver of the Newton system (assembled penalty).
        augmented_linear: Solver of the augmented system when the energy returns the penalty as
            a low-rank factor G (must be "ldlt" or "lu").
        armijo_c1: Sufficient-decrease constant c1 of the Armijo condition, in (0, 1/2).
        shrink: Step reduction factor of the backtracking line search, in (0, 1).
        max_line_search: Backtracking steps before the step is declared failed.
        step_growth: Largest multiple of a shifted step passing at ``alpha = 1`` that the line
            search tries, doubling while W falls (1 = none; 0 = by size, :func:`step_growth`).
        shift: Diagonal shift schedule ``A + tau I`` (fallback for indefinite / failed
            factorisations and non-descent directions).
        shift_decay: While ``||g|| > switch_rtol g_ref``, an iteration after one that needed
            ``tau_prev`` starts at ``tau_prev / shift_decay`` (> 1) without an unshifted
            attempt; nearer the minimum every iteration tries ``tau = 0`` first, keeping the
            quadratic tail (measured schedules: docs/notes/shift-schedule.md).
        linear_method: "direct" (sparse factorisation, ``linear``) or "multigrid" (CG with
            geometric multigrid, ``multigrid``; needs the ``hierarchy`` of the solver).
        multigrid: Options of the multigrid-preconditioned CG solve.
        modified: Reuse of one factorisation across iterations and frames (modified Newton).
        descent_tolerance: Descent test ``-g . dx >= descent_tolerance ||g|| ||dx||`` (a cosine).
        stagnation_iterations: Consecutive accepted steps without progress (W lowered by more
            than ``ROUNDOFF_FACTOR eps |W|`` or a new smallest ``||g||``) before the solve stops
            with :class:`ShellSolveError` naming the worst stencil.
        inertia_restart: Restart the shift ladder from a Lanczos estimate (first iteration;
            later ones for an outlier; direct path, :mod:`solvers.inertia_shift`).

    """

    rtol: float = 1e-8
    atol: float = 0.0
    gradient_scale: float = 0.0
    max_iterations: int = 200
    hessian: str = ""
    far_hessian: str = ""
    switch_rtol: float = 1e-3
    linear: LinearSolverOptions = field(default_factory=LinearSolverOptions)
    augmented_linear: LinearSolverOptions = field(
        default_factory=lambda: LinearSolverOptions(symmetric="ldlt"))
    armijo_c1: float = 1e-4
    shrink: float = 0.5
    max_line_search: int = 40
    step_growth: int = 0
    shift: ShiftOptions = field(default_factory=ShiftOptions)
    shift_decay: float = 10.0
    linear_method: str = "direct"
    multigrid: MultigridOptions = field(default_factory=MultigridOptions)
    modified: ModifiedNewtonOptions = field(default_factory=ModifiedNewtonOptions)
    descent_tolerance: float = 1e-10
    stagnation_iterations: int = 5
    inertia_restart: bool = False

    def __post_init__(self) -> None:
        _positive_checks(self)
        for name in ("hessian", "far_hessian"):
            value = getattr(self, name)
            if value and value not in HESSIAN_MODES:
                raise InputError(f"ShellNewtonOptions.{name}: expected '' or one of "
                                 f"{list(HESSIAN_MODES)}, got {value!r}")
        if not 0 < self.armijo_c1 < 0.5:
            raise InputError(f"ShellNewtonOptions.armijo_c1: must be in (0, 0.5), got "
                             f"{self.armijo_c1!r}")
        if not 0 < self.shrink < 1:
            raise InputError(f"ShellNewtonOptions.shrink: must be in (0, 1), got {self.shrink!r}")
        if self.augmented_linear.symmetric == "cholesky":
            raise InputError("ShellNewtonOptions.augmented_linear.symmetric: the augmented "
                             "system is indefinite; use 'ldlt' or 'lu'")
        if self.linear_method not in LINEAR_METHODS:
            raise InputError(f"ShellNewtonOptions.linear_method: expected one of "
                             f"{list(LINEAR_METHODS)}, got {self.linear_method!r}")
        if not self.shift_decay > 1:
            raise InputError(f"ShellNewtonOptions.shift_decay: must be > 1, got "
                             f"{self.shift_decay!r}")
        if self.step_growth < 0:
            raise InputError(f"ShellNewtonOptions.step_growth: must be >= 0 (0 = by size), got "
                             f"{self.step_growth!r}")


GROWTH_FROM_VERTICES: int = 20000
"""Shell vertex count from which ``step_growth = 0`` lengthens shifted steps (up to 8x;
docs/notes/solver-choice.md, "Lengthened shifted steps")."""


def step_growth(growth: int, vertices: int) -> int:
    """Return ``growth`` when >= 1; for 0 (by size) 8 from 20 000 vertices, else 1.

    A shifted step ``-(A + tau I)^{-1} g`` with ``tau`` near the most negative curvature is
    short in the soft directions; the ladder lowers ``tau`` by ``shift_decay`` per iteration
    only. Where the full step already lowers W, doubling it while W keeps falling (a
    lengthening line search, Nocedal & Wright 2006, sec. 3.5) makes up for that. The bound is
    :data:`GROWTH_FROM_VERTICES`.
    """
    if growth:
        return growth
    return 8 if vertices >= GROWTH_FROM_VERTICES else 1


def _positive_checks(opts: ShellNewtonOptions) -> None:
    """Validate the tolerances and counts of :class:`ShellNewtonOptions`."""
    for name in ("rtol", "atol", "gradient_scale", "descent_tolerance", "switch_rtol"):
        value = getattr(opts, name)
        if not (np.isfinite(value) and value >= 0):
            raise InputError(f"ShellNewtonOptions.{name}: must be finite and >= 0, got {value!r}")
    if opts.rtol == 0 and opts.atol == 0:
        raise InputError("ShellNewtonOptions.rtol: rtol and atol cannot both be 0")
    for name in ("max_iterations", "max_line_search", "stagnation_iterations"):
        if getattr(opts, name) < 1:
            raise InputError(f"ShellNewtonOptions.{name}: must be >= 1, got "
                             f"{getattr(opts, name)!r}")


@dataclass(frozen=True)
class NewtonIteration:
    """One Newton iteration.

    Attributes:
        energy: W at the start of the iteration.
        grad_norm: ||g|| at the start of the iteration.
        step: Accepted line-search step alpha.
        line_search_steps: Step reductions before acceptance (0 = full step).
        shift: Diagonal shift tau of the accepted direction (0 = plain Newton).
        factorizations: Factorisations in this iteration (1 + rejected attempts; 0 when the
            previous factorisation was reused, modified Newton).
        negative_pivots: Negative pivots of the first (unshifted) factorisation, None if
            unknown (LU backends).
        directional_derivative: g . dx of the accepted direction (< 0).
        krylov_iterations: CG iterations of this iteration (multigrid; 0 for direct).

    """

    energy: float
    grad_norm: float
    step: float
    line_search_steps: int
    shift: float
    factorizations: int
    negative_pivots: int | None
    directional_derivative: float
    krylov_iterations: int = 0


@dataclass(frozen=True)
class ShellSolveReport:
    """What :func:`minimize` did.

    Attributes:
        converged: Gradient tolerance met.
        reason: "gradient tolerance", "max_iterations", "stagnation", or the failure
            diagnostic.
        iterations: Newton iterations performed (accepted steps).
        energy: Final W.
        grad_norm: Final ||g||.
        tolerance: The gradient tolerance ``atol + rtol g_ref`` that was used.
        history: One :class:`NewtonIteration` per iteration.
        time_evaluate: Seconds in value/gradient/Hessian evaluations (order 2).
        time_line_search: Seconds in line-search energy evaluations.
        time_factorize: Seconds in factorisations (analysis + numeric).
        time_analysis: Seconds of that in the symbolic analysis.
        time_solve: Seconds in triangular solves.
        time_total: Wall time of the whole solve.
        krylov_fallbacks: Multigrid CG solves handed to the direct solver (CG failed).

    """

    converged: bool
    reason: str
    iterations: int
    energy: float
    grad_norm: float
    tolerance: float
    history: tuple[NewtonIteration, ...] = ()
    time_evaluate: float = 0.0
    time_line_search: float = 0.0
    time_factorize: float = 0.0
    time_analysis: float = 0.0
    time_solve: float = 0.0
    time_total: float = 0.0
    krylov_fallbacks: int = 0

    @property
    def grad_norms(self) -> np.ndarray:
        """||g_k|| for k = 0..iterations (the last one is the final gradient)."""
        return np.array([it.grad_norm for it in self.history] + [self.grad_norm])

    @property
    def energies(self) -> np.ndarray:
        """W_k for k = 0..iterations."""
        return np.array([it.energy for it in self.history] + [self.energy])

    @property
    def shifted_iterations(self) -> int:
        """Iterations whose accepted direction needed a diagonal shift."""
        return sum(1 for it in self.history if it.shift > 0)

    @property
    def factorizations(self) -> int:
        """Numeric factorisations over all iterations (shifted retries included)."""
        return sum(it.factorizations for it in self.history)

    @property
    def line_search_steps(self) -> int:
        """Total step reductions over all iterations."""
        return sum(it.line_search_steps for it in self.history)

    @property
    def reused_iterations(self) -> int:
        """Iterations that reused an earlier factorisation (modified Newton)."""
        return sum(1 for it in self.history if it.factorizations == 0)

    @property
    def krylov_iterations(self) -> int:
        """CG iterations over all Newton iterations (multigrid)."""
        return sum(it.krylov_iterations for it in self.history)

    def summary(self) -> str:
        """One line: converged flag, iterations, energy, gradient, shifts, timings."""
        return (f"converged={self.converged} ({self.reason}) it={self.iterations} "
                f"W={self.energy:.12e} |g|={self.grad_norm:.3e} shifts={self.shifted_iterations} "
                f"factorizations={self.factorizations} "
                f"ls={self.line_search_steps} t_eval={self.time_evaluate:.3f}s "
                f"t_fact={self.time_factorize:.3f}s t_solve={self.time_solve:.3f}s "
                f"t_total={self.time_total:.3f}s"
                + (f" reused={self.reused_iterations}" if self.reused_iterations else "")
                + (f" cg={self.krylov_iterations} cg_fallbacks={self.krylov_fallbacks}"
                   if self.krylov_iterations else ""))


class ShellSolveError(SolverError):
    """No progress was possible; carries the best state and the report so far.

    Attributes:
        x: Best positions (n, 3) reached.
        report: The :class:`ShellSolveReport` up to the failure.

    """

    def __init__(self, message: str, x: np.ndarray, report: ShellSolveReport) -> None:
        super().__init__(message)
        self.x = x
        self.report = report


@dataclass
class _Timers:
    """Mutable wall-time accumulators of one solve (seconds)."""

    evaluate: float = 0.0
    line_search: float = 0.0
    start: float = field(default_factory=time.perf_counter)
    linear_start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """(factorise, analysis, solve) totals of the long-lived linear solvers at the start."""
    fallbacks_start: int = 0
    """Multigrid fallbacks to the direct solve before this solve."""


@dataclass
class _Progress:
    """Counts consecutive accepted steps without progress (stagnation test).

    Attributes:
        best_grad: Smallest ``||g||`` seen so far.
        stalled: Consecutive steps that neither lowered W beyond round-off nor ``||g||``.

    """

    best_grad: float
    stalled: int = 0

    def update(self, w_old: float, w_new: float, grad_norm: float) -> int:
        """Record one accepted step ``W: w_old -> w_new`` with new ``||g||``; return stalled."""
        lowered = w_old - w_new > ROUNDOFF_FACTOR * np.finfo(float).eps * abs(w_old)
        self.stalled = 0 if lowered or grad_norm < self.best_grad else self.stalled + 1
        self.best_grad = min(self.best_grad, grad_norm)
        return self.stalled


@dataclass(frozen=True)
class _Direction:
    """A direction that passed the line search: ``x + alpha dx`` with ``W = energy``."""

    dx: np.ndarray
    slope: float
    alpha: float
    energy: float
    reductions: int


@dataclass(frozen=True)
class _Step:
    """An accepted Newton step."""

    x: np.ndarray
    energy: float
    record: NewtonIteration


class _LinearSystem:
    """Factorise / solve the Newton system, plain or augmented, solver built once."""

    def __init__(self, options: ShellNewtonOptions) -> None:
        self.options = options
        self.plain: SparseDirectSolver | None = None
        self.augmented: AugmentedPenaltySolver | None = None

    def factorize(self, ev: EnergyEval, tau: float) -> FactorReport:
        """Factorise ``A + tau I`` (or its augmented form when ``ev.penalty_factor`` is set)."""
        hess, g = ev.hess, ev.penalty_factor
        if hess is None:
            raise InputError("energy.evaluate(order=2) returned no Hessian")
        if g is None:
            if self.plain is None:
                self.plain = SparseDirectSolver(hess, self.options.linear)
            return self.plain.factorize(hess, tau)
        if self.augmented is None:
            self.augmented = AugmentedPenaltySolver(hess, g, self.options.augmented_linear)
        return self.augmented.factorize(hess, g, tau)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve with the last factorisation."""
        solver = self.augmented if self.augmented is not None else self.plain
        assert solver is not None  # factorize() ran first (internal invariant)
        return solver.solve(rhs)

    def _solvers(self) -> list[SparseDirectSolver]:
        """Return the underlying sparse solvers built so far."""
        out = [self.plain] if self.plain is not None else []
        return out + ([self.augmented.solver] if self.augmented is not None else [])

    def times(self) -> tuple[float, float, float]:
        """Accumulated (factorise, analysis, solve) seconds of every solver."""
        stats = [s.stats for s in self._solvers()]
        return (sum(s.analysis_time + s.numeric_time for s in stats),
                sum(s.analysis_time for s in stats), sum(s.solve_time for s in stats))


def _grad_norm(ev: EnergyEval) -> float:
    """Euclidean norm of the gradient of an order >= 1 evaluation."""
    if ev.grad is None:
        raise InputError("energy.evaluate(order=2) returned no gradient")
    return float(np.linalg.norm(ev.grad))


FOLD_MARGIN: float = 1e-3
"""A hinge whose bend angle is within this of +-pi [rad] counts as folded flat."""


def worst_stencil(energy: object, grad: np.ndarray, x: np.ndarray) -> str:
    """Name the vertex of largest ``|g_i|`` and its incident face of lowest rest quality.

    The face (quality ``4 sqrt(3) A / sum |e|^2``, :func:`models.shell.rest.face_quality`) is
    named when ``energy`` has ``topology.faces`` and ``rest.positions`` (``ShellEnergy``).
    A hinge folded flat at the positions ``x`` is named too (:func:`folded_hinge`).
    """
    per_vertex = np.linalg.norm(grad.reshape(-1, 3), axis=1)
    v = int(np.argmax(per_vertex))
    return (f"vertex {v} (|g_i| = {per_vertex[v]:.3e})" + _worst_face(energy, v)
            + folded_hinge(energy, x))


def folded_hinge(energy: object, x: np.ndarray) -> str:
    """``"; hinge h [i, j, k, l] folded flat (...)"`` for the hinge nearest to ``|theta| = pi``.

    The bend angle lives in ``(-pi, pi]`` (:mod:`models.shell.hinge_angle`): at ``+-pi`` the
    two faces lie back to back and ``(theta - theta0)^2`` jumps, so no line search crosses
    it (a shell Newton on an unconverged two-way body can stall there). Empty when no hinge is
    within :data:`FOLD_MARGIN` of +-pi or ``energy`` has no ``topology.hinges``.
    """
    hinges = getattr(getattr(energy, "topology", None), "hinges", None)
    if hinges is None or len(hinges) == 0:
        return ""
    hinges = np.asarray(hinges)
    gap = np.pi - np.abs(hinge_angles(np.asarray(x).reshape(-1, 3), hinges))
    h = int(np.argmin(gap))
    if gap[h] > FOLD_MARGIN:
        return ""
    return (f"; hinge {h} {hinges[h].tolist()} is folded flat (bend angle "
            f"{np.pi - gap[h]:.6f} rad, pi - {gap[h]:.1e}), where the bending energy is "
            f"discontinuous: the target drives the faces back to back")


def _worst_face(energy: object, vertex: int) -> str:
    """``", face f [i, j, k] (rest quality q)"`` of the lowest-quality face of ``vertex``."""
    faces = getattr(getattr(energy, "topology", None), "faces", None)
    rest = getattr(getattr(energy, "rest", None), "positions", None)
    if faces is None or rest is None:
        return ""
    faces = np.asarray(faces)
    star = np.flatnonzero((faces == vertex).any(axis=1))
    if star.size == 0:
        return ""
    q = face_quality(np.asarray(rest), faces[star])
    f = int(star[np.argmin(q)])
    return f", face {f} {faces[f].tolist()} (rest quality {q.min():.3e})"


class ShellNewtonSolver:
    """Newton / SQP solver bound to one energy; keeps its factorisation across frames.

    Args:
        energy: The shell energy (fixed Hessian pattern).
        options: Solver options.
        hierarchy: The subdivision hierarchy the shell was built by (needed by
            ``linear_method = "multigrid"``; its finest level must be the shell).
        krylov: A CG solver of the Newton system to use instead of the one
            ``linear_method`` names (the joint body-shell system of the two-way coupling,
            :class:`solvers.joint_krylov.JointKrylovSystem`).

    Attributes:
        hessian_product: ``(ev, v) -> (A + G^T G) v``, the full Hessian's product with a
            (3n,) vector, for the Lanczos estimate of the shift ladder's restart; a solve
            split over ranks sets its distributed product.

    """

    def __init__(self, energy: ShellEnergyLike, options: ShellNewtonOptions | None = None,
                 hierarchy: ShellHierarchy | None = None,
                 krylov: KrylovSystem | None = None) -> None:
        self.energy = energy
        self.options = options or ShellNewtonOptions()
        self.direct = _LinearSystem(self.options)
        self.linear: NewtonSystem = self.direct
        self.krylov: KrylovSystem | None = krylov
        if krylov is not None:
            self.linear = krylov
        elif self.options.linear_method == "multigrid":
            if hierarchy is None:
                raise InputError("ShellNewtonOptions.linear_method: 'multigrid' needs the "
                                 "subdivision hierarchy (ShellNewtonSolver(..., hierarchy=))")
            self.krylov = MultigridLinearSystem(hierarchy.prolongations(),
                                                self.options.multigrid, fallback=self.direct,
                                                geometry=(hierarchy.vertices, hierarchy.faces))
            self.linear = self.krylov
        self.hessian_product: Callable[[EnergyEval, np.ndarray], np.ndarray] = \
            lambda ev, v: shifted_product(ev, 0.0, v)
        self._last_shift = 0.0
        self._first_shift = 0.0  # where the next solve's first iteration starts its shifts
        self._factor_age = 0  # iterations served by the current factorisation (0 = none)
        self._refresh = True  # the next iteration must factorise (modified Newton)
        self._mode_now = ""
        self._target = 0.0  # gradient tolerance of the running solve (multigrid forcing)
        self._diagonal_scale = DiagonalScale()
        self._growth = step_growth(self.options.step_growth, energy.n_vertices)

    @property
    def shift_state(self) -> np.ndarray:
        """The shift schedule's memory across solves: ``[tau_last, tau_first]``.

        ``tau_last``: the last accepted shift (the next iteration starts from ``tau_last /
        shift_decay``); ``tau_first``: the one the last solve's first iteration accepted (the
        next solve's first iteration starts a rung below it). A run resumed from a checkpoint
        sets it back to take the same steps as the run it continues.
        """
        return np.array([self._last_shift, self._first_shift])

    @shift_state.setter
    def shift_state(self, value: np.ndarray) -> None:
        last, first = (float(v) for v in np.asarray(value, dtype=np.float64).reshape(2))
        if not (np.isfinite(last) and np.isfinite(first) and last >= 0.0 and first >= 0.0):
            raise InputError(f"shift_state: expected two finite shifts >= 0, got {value!r}")
        self._last_shift, self._first_shift = last, first

    def use_phase_space(self, active: bool) -> None:
        """Set whether the phase space (if any) serves the coming solve from its start.

        Otherwise it joins at the solve's first negative curvature
        (:meth:`solvers.multigrid.KrylovBase.use_phase_space`).
        """
        if isinstance(self.krylov, KrylovBase):
            self.krylov.use_phase_space(active)

    @property
    def phase_space_in_use(self) -> bool:
        """Whether the multigrid has a phase space and it serves the solves now."""
        k = self.krylov
        return isinstance(k, KrylovBase) and k.phase is not None and k.phase_active

    def _reuse_next(self) -> bool:
        """Whether the next iteration will try the previous factorisation (modified Newton)."""
        mod = self.options.modified
        return mod.enabled and not self._refresh and 0 < self._factor_age < mod.max_age

    def _evaluate(self, x: np.ndarray, timers: _Timers, mode: str, order: int = 2
                  ) -> EnergyEval:
        """Evaluate W (order 0-2) with Hessian ``mode`` ("" = the energy's default), timed."""
        start = time.perf_counter()
        self._mode_now = mode
        ev = self.energy.evaluate(x.reshape(-1, 3), order=order, hessian=mode or None)
        timers.evaluate += time.perf_counter() - start
        if not (np.isfinite(ev.value) and ev.grad is not None and np.all(np.isfinite(ev.grad))):
            raise SolverError(f"shell energy is not finite at the current state (W={ev.value})")
        return ev

    def minimize(self, x0: np.ndarray) -> tuple[np.ndarray, ShellSolveReport]:
        """Minimise W from ``x0`` ((n, 3) or flat); return ``(x (n, 3), report)``.

        Raises:
            ShellSolveError: no direction/shift gave an Armijo step, or the solve stagnated
                (see ``stagnation_iterations``); carries the best x and the report.
            SolverError: W or its gradient is not finite at x0.

        """
        x = np.array(x0, dtype=np.float64).reshape(-1)
        if x.size != 3 * self.energy.n_vertices:
            raise InputError(f"x0: expected {self.energy.n_vertices} vertices, got shape "
                             f"{np.shape(x0)}")
        if self.krylov is not None:
            self.krylov.reset_forcing()
        self._refresh = False  # a new frame may start with the last frame's factorisation
        timers, history = _Timers(linear_start=self.linear.times(),
                                  fallbacks_start=self._fallbacks()), list[NewtonIteration]()
        opts = self.options
        ev = self._evaluate(x, timers, opts.far_hessian or opts.hessian)
        tol = self._tolerance(_grad_norm(ev))
        self._target = tol
        switch = opts.switch_rtol * (opts.gradient_scale or _grad_norm(ev))
        if opts.far_hessian and _grad_norm(ev) <= switch:
            ev = self._evaluate(x, timers, opts.hessian)
        progress = _Progress(_grad_norm(ev))
        while _grad_norm(ev) > tol:
            if len(history) >= self.options.max_iterations:
                return x.reshape(-1, 3), self._report(False, "max_iterations", ev, tol,
                                                      history, timers)
            step = self._iterate(x, ev, timers, near=_grad_norm(ev) <= switch,
                                 first=not history)
            if step is None:
                report = self._report(False, "no descent step after all shifts", ev, tol,
                                      history, timers)
                raise ShellSolveError(f"shell Newton: no Armijo step at iteration "
                                      f"{len(history)}; {report.summary()}", x.reshape(-1, 3),
                                      report)
            history.append(step.record)
            x = step.x
            mode = self._mode(_grad_norm(ev), switch)
            del ev  # the last Hessian goes before the next one is assembled (peak memory)
            ev = self._next_evaluation(x, timers, mode, step.record.grad_norm)
            if progress.update(step.record.energy, ev.value, _grad_norm(ev)) \
                    >= opts.stagnation_iterations:
                self._stagnated(x, ev, tol, history, timers)
        return x.reshape(-1, 3), self._report(True, "gradient tolerance", ev, tol, history,
                                              timers)

    def _next_evaluation(self, x: np.ndarray, timers: _Timers, mode: str,
                         previous_norm: float) -> EnergyEval:
        """Evaluate the new iterate; the Hessian is skipped when the factorisation is reused.

        Modified Newton refreshes the factorisation when ``||g_{k+1}|| > refresh_ratio
        ||g_k||``; only then (or when the factorisation is too old) is the order-2
        evaluation needed.
        """
        mod = self.options.modified
        if not (mod.enabled and 0 < self._factor_age < mod.max_age):
            return self._evaluate(x, timers, mode)
        ev = self._evaluate(x, timers, mode, order=1)
        self._refresh = _grad_norm(ev) > mod.refresh_ratio * previous_norm
        return self._evaluate(x, timers, mode) if self._refresh else ev

    def _stagnated(self, x: np.ndarray, ev: EnergyEval, tol: float,
                   history: list[NewtonIteration], timers: _Timers) -> None:
        """Raise :class:`ShellSolveError` for a stagnated solve, naming the worst stencil."""
        assert ev.grad is not None  # order-2 evaluation
        report = self._report(False, "stagnation", ev, tol, history, timers)
        raise ShellSolveError(
            f"shell Newton: no progress in {self.options.stagnation_iterations} iterations "
            f"(W changes within round-off, ||g|| = {report.grad_norm:.3e} > {tol:.3e}); worst "
            f"stencil: {worst_stencil(self.energy, ev.grad, x)}; {report.summary()}",
            x.reshape(-1, 3), report)

    def _mode(self, grad_norm: float, switch: float) -> str:
        """Hessian mode of the next evaluation: ``far_hessian`` until ``||g|| <= switch``.

        Decided on the gradient of the previous iterate (the new one is not known before
        evaluating it), so the switch happens one iteration after crossing the threshold.
        """
        if self.options.far_hessian and grad_norm > switch:
            return self.options.far_hessian
        return self.options.hessian

    def _tolerance(self, g0: float) -> float:
        """``atol + rtol g_ref`` with ``g_ref`` the scale option or the initial gradient."""
        scale = self.options.gradient_scale or g0
        return self.options.atol + self.options.rtol * scale

    def _iterate(self, x: np.ndarray, ev: EnergyEval, timers: _Timers, near: bool,
                 first: bool = False) -> _Step | None:
        """One Newton iteration: the previous factorisation (modified Newton) or a new one.

        ``near``: ``||g|| <= switch_rtol g_ref``; there the unshifted Hessian is always tried
        first (quadratic convergence), farther away the last successful shift is reused
        (:func:`solvers.linear.shift_candidates`). ``first``: the solve's first iteration, whose
        ladder may restart from a Lanczos estimate (``inertia_restart``; later iterations only
        for an outlier).
        """
        assert ev.grad is not None  # order >= 1 evaluation
        if self.krylov is not None:
            self.krylov.set_gradient_norm(float(np.linalg.norm(ev.grad)), self._target)
            if self.krylov.phase is not None:  # its test fields follow x
                self.krylov.set_state(x, getattr(self.energy, "target", None))
        cg_before = self._krylov_count()
        if self._reuse_next():
            found = self._direction(x, ev, timers, self._last_shift)
            if found is not None:
                self._factor_age += 1
                return self._step(x, ev, found, self._last_shift, 0, None, cg_before)
        if ev.hess is None:  # order-1 evaluation for a reuse that failed
            ev = self._evaluate(x, timers, self._mode_now)
        return self._factorize_and_step(x, ev, timers, cg_before, near, first)

    def _factorize_and_step(self, x: np.ndarray, ev: EnergyEval, timers: _Timers,
                            cg_before: int, near: bool, first: bool = False) -> _Step | None:
        """Factorise with shifts until a direction passes the descent test and line search.

        The schedule is :func:`solvers.linear.shift_candidates` from ``tau_prev /
        shift_decay``, with the unshifted attempt first when ``near`` (or when that start is
        below the schedule's first shift). A solve's ``first`` iteration starts at least one
        rung (``shift.growth``) below the shift the previous solve's first iteration accepted:
        a warm-started frame's first Hessian is made indefinite by its target's motion much
        like the frame before's, so it pays one failed attempt where it needs the same shift
        (instead of the climb from ``tau_0``), none where it needs less (the start follows the
        need down a rung per frame), and never starts above that rung (an overshoot costs an
        iteration per ``shift_decay`` of the return).
        """
        assert ev.hess is not None  # order-2 evaluation
        scale = self._diagonal_scale(ev.hess)
        taus: list[float] = []
        found: list[_Direction] = []

        def factorize(tau: float) -> FactorReport:
            taus.append(tau)
            return self.linear.factorize(ev, tau)

        def accept(report: FactorReport) -> bool:
            direction = self._direction(x, ev, timers, taus[-1]) if report.usable_spd else None
            found.extend([direction] if direction is not None else [])
            return direction is not None

        restartable = self.options.inertia_restart and self.krylov is None
        start = self._last_shift / self.options.shift_decay
        if first:
            start = max(start, self._first_shift / self.options.shift.growth)
        floor = None if first else max(self.options.shift.initial * scale, self._last_shift)
        reports = factorize_with_shift(factorize, scale, self.options.shift, start,
                                       accept, zero_first=near or None,
                                       restart=self._restart(ev, floor) if restartable else None)
        if not found:
            self._factor_age = 0
            return None
        self._last_shift, self._factor_age = taus[-1], 1
        if first:
            self._first_shift = taus[-1]
        return self._step(x, ev, found[0], taus[-1], len(reports),
                          reports[0].negative_pivots, cg_before)

    def _restart(self, ev: EnergyEval,
                 floor: float | None) -> Callable[[FactorReport, list[float]], list[float]]:
        """Shifts from the Lanczos estimate of the full Hessian's smallest eigenvalue.

        Used on the direct path after an indefinite first attempt
        (:func:`solvers.inertia_shift.restart_ladder`, given the rungs left); the full Hessian
        is ``A + G^T G`` when the penalty comes as the factor G (its product
        :attr:`hessian_product`). ``floor`` None: a solve's first iteration, where any
        estimate restarts a few extra negative pivots and skips the rungs it proves
        indefinite for many; else a later one, where only an outlier beyond ``OUTLIER
        max(tau, floor)`` restarts, ``tau`` the attempt's shift and ``floor`` the larger of
        the ladder's first rung and the previous iteration's shift (an unshifted attempt near
        the minimum is measured against the shift the path came down from).
        """
        assert ev.hess is not None and ev.grad is not None  # order-2 evaluation
        n = ev.grad.size

        def restart(report: FactorReport, ladder: list[float]) -> list[float]:
            beyond = 0.0 if floor is None else OUTLIER * max(report.shift, floor)
            return restart_ladder(report, lambda v: self.hessian_product(ev, v), n,
                                  self.options.shift, beyond, ladder)
        return restart

    def _direction(self, x: np.ndarray, ev: EnergyEval, timers: _Timers,
                   tau: float) -> _Direction | None:
        """Solve with the current factorisation (shift ``tau``); descent test and line search."""
        assert ev.grad is not None  # order >= 1 evaluation
        dx = self.linear.solve(-ev.grad)
        slope = float(ev.grad @ dx)
        if not self._is_descent(ev.grad, dx, slope):
            return None
        found = self._line_search(x, ev.value, dx, slope, timers, tau > 0)
        if found is None:
            return None
        return _Direction(dx, slope, *found)

    def _step(self, x: np.ndarray, ev: EnergyEval, d: _Direction, tau: float,
              factorizations: int, negatives: int | None, cg_before: int) -> _Step:
        """Build the accepted step and its :class:`NewtonIteration` record."""
        assert ev.grad is not None  # order >= 1 evaluation
        record = NewtonIteration(ev.value, float(np.linalg.norm(ev.grad)), d.alpha,
                                 d.reductions, tau, factorizations, negatives, d.slope,
                                 self._krylov_count() - cg_before)
        return _Step(x + d.alpha * d.dx, d.energy, record)

    def _krylov_count(self) -> int:
        """CG iterations so far (0 without multigrid)."""
        return sum(self.krylov.stats.iterations) if self.krylov is not None else 0

    def _fallbacks(self) -> int:
        """Multigrid fallbacks to the direct solve so far."""
        return self.krylov.stats.fallbacks if self.krylov is not None else 0

    def _is_descent(self, g: np.ndarray, dx: np.ndarray, slope: float) -> bool:
        """``-g . dx >= descent_tolerance ||g|| ||dx||`` and dx finite."""
        if not np.all(np.isfinite(dx)):
            return False
        return -slope >= self.options.descent_tolerance * np.linalg.norm(g) * np.linalg.norm(dx)

    def _line_search(self, x: np.ndarray, w0: float, dx: np.ndarray, slope: float,
                     timers: _Timers, shifted: bool = False) -> tuple[float, float, int] | None:
        """Backtracking Armijo: ``(alpha, W(x + alpha dx), reductions)`` or None.

        A ``shifted`` step passing at ``alpha = 1`` is doubled while W falls, up to the
        solver's step growth (:func:`step_growth`); ``alpha`` may then exceed 1.
        """
        start = time.perf_counter()
        noise = ROUNDOFF_FACTOR * np.finfo(float).eps * abs(w0)
        alpha = 1.0
        try:
            for j in range(self.options.max_line_search):
                w = float(self.energy.value((x + alpha * dx).reshape(-1, 3)))
                if np.isfinite(w) and w <= w0 + self.options.armijo_c1 * alpha * slope + noise:
                    while j == 0 and shifted and 2 * alpha <= self._growth:
                        longer = float(self.energy.value((x + 2 * alpha * dx).reshape(-1, 3)))
                        if not (np.isfinite(longer) and longer < w):
                            break
                        alpha, w = 2 * alpha, longer
                    return alpha, w, j
                alpha *= self.options.shrink
            return None
        finally:
            timers.line_search += time.perf_counter() - start

    def _report(self, converged: bool, reason: str, ev: EnergyEval, tol: float,
                history: list[NewtonIteration], timers: _Timers) -> ShellSolveReport:
        """Freeze the run into a :class:`ShellSolveReport`."""
        factorize, analysis, solve = (now - before for now, before
                                      in zip(self.linear.times(), timers.linear_start,
                                             strict=True))
        return ShellSolveReport(
            converged=converged, reason=reason, iterations=len(history), energy=ev.value,
            grad_norm=_grad_norm(ev), tolerance=tol, history=tuple(history),
            time_evaluate=timers.evaluate, time_line_search=timers.line_search,
            time_factorize=factorize, time_analysis=analysis, time_solve=solve,
            time_total=time.perf_counter() - timers.start,
            krylov_fallbacks=self._fallbacks() - timers.fallbacks_start)


def minimize(energy: ShellEnergyLike, x0: np.ndarray,
             options: ShellNewtonOptions | None = None) -> tuple[np.ndarray, ShellSolveReport]:
    """Minimise the shell energy from ``x0`` (warm start); see the module docstring.

    For a sequence of frames keep one :class:`ShellNewtonSolver` instead, so the symbolic
    factorisation is reused across frames too.

    Args:
        energy: ``models.shell.energy.ShellEnergy`` (or anything with ``evaluate``/``value``).
        x0: Start positions (n, 3).
        options: Solver options.

    Returns:
        ``(x, report)`` with x the (n, 3) minimiser.

    Raises:
        ShellSolveError: no progress possible (carries the best state and the report).

    """
    return ShellNewtonSolver(energy, options).minimize(x0)
