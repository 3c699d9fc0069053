"""Newton's method for the coarse body's total potential through PETSc SNES.

The body's discrete problem is the minimisation of one energy ``Pi(u)`` (a UFL form, see
``models/body.py``): the residual is ``dPi/du`` and the Jacobian ``d^2 Pi/du^2``, both from
``ufl.derivative``. SNES (``newtonls``) runs Newton with the MUMPS LU for the linear solves,
or CG + GAMG once the first factorisation showed the LU too costly
(``NewtonOptions.method``, :mod:`solvers.body_linear`).

Line search (``NewtonOptions.line_search_type``):

* ``"energy"`` (default): our backtracking Armijo search on the assembled energy, run in the
  SNES line-search pre-check (``SNESLineSearchSetPreCheck``) so that SNES's own ``basic``
  search then takes the scaled step. With the Newton step ``du`` and ``s = dPi(u).du < 0``
  it accepts the first ``l = 1, 1/2, 1/4, ...`` with (Dennis & Schnabel 1996, Alg. A6.3.1)

      Pi(u + l du) <= Pi(u) + c1 l s,

  where ``Pi = +inf`` as soon as a quadrature point has ``det F <= 0``, so the iterate never
  leaves the admissible set ``J > 0``. Near the solution the Newton decrease
  ``s/2 ~ |r|^2 / k`` falls below the round-off of the assembled energy (which is
  ``~1e-16 * sum |psi| dX``, e.g. ``(mu + lambda) |Omega|``, not ``1e-16 |Pi|``), and a strict
  Armijo test then stalls (so does PETSc's ``bt``: docs/notes/body-line-search.md). So
  when ``|Pi(u + l du) - Pi(u)| <= eps_Pi`` with ``eps_Pi = energy_roundoff * (|Pi(u)| +
  energy_scale)`` (energy indistinguishable from
  noise), the step is accepted iff the residual norm decreases.
* ``"petsc_bt"``: PETSc's ``bt`` search on the same objective (``SNESSetObjective``).

Extra quadratic term (:class:`QuadraticTerm`, :meth:`EnergyNewton.set_quadratic_term`): an
energy ``E(u) = 1/2 u^T K u - c^T u + e0`` given as a PETSc matrix ``K`` and vector ``c`` in
the dof layout of ``u`` (e.g. the embedded shell's cluster penalty
``k_P ||H (x - B (X + u))||^2`` with the shell ``x`` fixed, :mod:`models.coupling`). It is
added to the objective, to the residual (``K u - c``, free rows only: Dirichlet rows keep
``u - g``) and to the Jacobian (``K`` with the Dirichlet rows and columns removed, so the
identity rows of the Dirichlet dofs stay). The Jacobian matrix is recreated once with the
union of both sparsity patterns when a term is set.

``solve()`` never trusts SNES: it reads the converged reason and checks ``min det F`` and the
finiteness of the energy after every solve, and reports the outcome; the caller (``Body``)
restores its last good state and cuts the step on failure.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from meshes.errors import InputError
from models.backend import (
    PETSc,
    assemble_snes_residual,
    dolfinx,
    global_min_on_cells,
    global_scalar,
    petsc_error_message,
    quadrature_expression,
    set_from_options,
    ufl,
    with_facet_domains,
)
from models.quadratic import QuadraticTerm
from solvers.body_linear import IterativeBodySolve, choose_body_method

_COUNTER = itertools.count()


@dataclass(frozen=True)
class NewtonOptions:
    """Options of the body's Newton solver.

    Attributes:
        rtol: Relative tolerance on the residual norm ``|dPi/du|`` (SNES ``snes_rtol``) [-].
        atol: Absolute tolerance on the residual norm [N] (SNES ``snes_atol``).
        stol: Tolerance on the relative Newton step ``|du| / |u|`` [-], counted only for a
            full (unscaled) Newton step: it ends the iteration when the residual sits at its
            round-off floor above ``atol``. 0 disables it.
        max_it: Maximum Newton iterations per solve.
        line_search: Energy-based backtracking line search (energy ``+inf`` where
            ``det F <= 0``) when True; full Newton steps (``basic``) when False.
        line_search_type: ``"energy"`` (our Armijo search with round-off allowance, default)
            or ``"petsc_bt"`` (PETSc's ``bt`` on the energy objective); see module doc.
        armijo_c1: Sufficient-decrease constant ``c1`` of the Armijo test [-].
        energy_roundoff: Relative width of the energy noise band ``eps_Pi`` [-] (module doc).
        max_backtracks: Step halvings inside one line search before it fails.
        max_halvings: How many times a failed step (time step or load increment) is halved
            and retried before ``SolverError`` is raised.
        linear_solver: Direct solver package for the Newton systems: ``"mumps"`` or
            ``"superlu_dist"`` (LU, in the wheel).
        method: ``"auto"`` (the MUMPS LU, replaced by CG + GAMG after the first
            factorisation if it cost more than :data:`solvers.body_linear.ITERATIVE_FLOPS`),
            ``"direct"`` (the LU always) or ``"iterative"`` (CG + GAMG from the start; the LU
            where CG fails): :mod:`solvers.body_linear`. With expert ``petsc`` options they
            choose the solver and ``method`` must stay ``"auto"`` (no choice is made).
        petsc: PETSc options of the SNES / KSP / PC, set after the ones these fields stand
            for (:meth:`petsc_options`), e.g. ``{"ksp_type": "cg", "pc_type": "gamg"}``. An
            option PETSc refuses, or one none of the SNES, KSP, PC and factor reads (a
            misspelt name, a value of the wrong kind), is an ``InputError`` naming it.

    """

    rtol: float = 1.0e-9
    atol: float = 1.0e-10
    stol: float = 1.0e-10
    max_it: int = 50
    line_search: bool = True
    line_search_type: str = "energy"
    armijo_c1: float = 1.0e-4
    energy_roundoff: float = 1.0e-12
    max_backtracks: int = 40
    max_halvings: int = 8
    linear_solver: str = "mumps"
    method: str = "auto"
    petsc: dict[str, str | int | float | bool] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("rtol", "atol", "stol", "armijo_c1", "energy_roundoff"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"newton.{name} must be finite and >= 0, got {value}")
        if self.max_it < 1:
            raise InputError(f"newton.max_it must be >= 1, got {self.max_it}")
        if self.max_halvings < 0:
            raise InputError(f"newton.max_halvings must be >= 0, got {self.max_halvings}")
        if self.line_search_type not in ("energy", "petsc_bt"):
            raise InputError("newton.line_search_type must be 'energy' or 'petsc_bt', "
                             f"got {self.line_search_type!r}")
        if self.max_backtracks < 1:
            raise InputError(f"newton.max_backtracks must be >= 1, got {self.max_backtracks}")
        if self.linear_solver not in ("mumps", "superlu_dist"):
            raise InputError("newton.linear_solver must be 'mumps' or 'superlu_dist', "
                             f"got {self.linear_solver!r}")
        if self.method not in ("auto", "direct", "iterative"):
            raise InputError("newton.method must be 'auto', 'direct' or 'iterative', "
                             f"got {self.method!r}")
        if self.method == "iterative" and (self.petsc or self.linear_solver != "mumps"):
            raise InputError("newton.method = 'iterative' falls back on the MUMPS LU and "
                             "sets the KSP and PC itself: leave newton.petsc and "
                             "newton.linear_solver unset")
        if self.petsc:
            check_petsc_options(self.petsc_options(), self.petsc)

    @property
    def chooses_method(self) -> bool:
        """Whether the solver picks direct or iterative after its first factorisation."""
        return self.method == "auto" and not self.petsc and self.linear_solver == "mumps"

    @property
    def matrix_kind(self) -> str:
        """PETSc type of the Jacobian: 3 x 3 blocks (``"baij"``) for the MUMPS LU.

        One insertion per node pair instead of nine entries makes the insertion several times
        cheaper (docs/notes/body-assembly.md); MUMPS factorises block matrices as they are.
        SuperLU_dist and solvers chosen by expert options (``petsc``) keep ``"aij"``.
        """
        return "baij" if self.linear_solver == "mumps" and not self.petsc else "aij"

    @property
    def uses_petsc_bt(self) -> bool:
        """Whether PETSc's ``bt`` line search on the objective is in use."""
        return self.line_search and self.line_search_type == "petsc_bt"

    def petsc_options(self) -> dict[str, Any]:
        """Return the SNES/KSP options these settings stand for."""
        return {
            "snes_type": "newtonls",
            "snes_linesearch_type": "bt" if self.uses_petsc_bt else "basic",
            "snes_rtol": self.rtol,
            "snes_atol": self.atol,
            "snes_stol": self.stol,
            "snes_max_it": self.max_it,
            "snes_max_funcs": 100 * self.max_it + 100,
            "ksp_type": "preonly",
            "pc_type": "lu",
            "pc_factor_mat_solver_type": self.linear_solver,
            **self.petsc,
        }


@dataclass(frozen=True)
class NewtonResult:
    """Outcome of one Newton solve.

    Attributes:
        converged: SNES reported convergence, the energy is finite and ``min det F > 0``.
        reason: SNES converged reason (> 0 converged, < 0 diverged, see ``SNESConvergedReason``).
        iterations: Newton iterations taken.
        residual_norm: Final residual norm ``|dPi/du|`` [N].
        energy: Final energy ``Pi(u)`` [J] (``inf`` when inadmissible).
        min_det_f: Minimum of ``det F`` over all quadrature points [-].

    """

    converged: bool
    reason: int
    iterations: int
    residual_norm: float
    energy: float
    min_det_f: float

    def describe(self) -> str:
        """One-line diagnostic for error messages and logs."""
        return (f"SNES reason={self.reason}, iterations={self.iterations}, "
                f"residual={self.residual_norm:.3e}, energy={self.energy:.6e}, "
                f"min det F={self.min_det_f:.3e}")


def bc_rows(bcs: list[Any], u: Any) -> np.ndarray:
    """Global PETSc indices of the Dirichlet dofs of ``bcs`` owned by this rank."""
    start = u.x.petsc_vec.getOwnershipRange()[0]
    rows = [bc.dof_indices()[0][:bc.dof_indices()[1]] for bc in bcs]
    local = np.unique(np.concatenate(rows)) if rows else np.zeros(0, dtype=np.int64)
    return (local + start).astype(PETSc.IntType)


def configure(snes: Any, options: dict[str, Any], expert: dict[str, Any]) -> dict[str, Any]:
    """Set ``options`` on ``snes`` (its prefix) and check the ``expert`` ones PETSc read.

    Returns the expert ``mat_*`` options, which the factor reads at its first set-up (check
    them then with :func:`unread_options`).

    Raises:
        InputError: PETSc refused an option, or an expert one is not read (the options of
            the prefix are then removed from PETSc's database).

    """
    prefix = snes.getOptionsPrefix()
    try:
        set_from_options(snes, options)
        return unread_options(prefix, expert, factor=False)
    except PETSc.Error as err:
        clear_options(prefix, options)
        raise InputError(f"newton.options.petsc {expert}: PETSc refused them: "
                         f"{petsc_error_message(err)}") from None
    except InputError:
        clear_options(prefix, options)
        raise


def check_petsc_options(options: dict[str, Any], expert: dict[str, Any]) -> None:
    """Check the expert options on a bare SNES (no problem attached) before any solver exists.

    Raises:
        InputError: as :func:`configure` (a scene's bad option is refused when it is read).

    """
    snes = PETSc.SNES().create(PETSc.COMM_SELF)
    snes.setOptionsPrefix(f"body_newton_check_{next(_COUNTER)}_")
    try:
        configure(snes, options, expert)
        clear_options(snes.getOptionsPrefix(), options)
    finally:
        snes.destroy()


def clear_options(prefix: str, options: dict[str, Any]) -> None:
    """Delete ``options`` under ``prefix`` from PETSc's options database (where set)."""
    table = PETSc.Options()
    for key in options:
        if table.hasName(f"{prefix}{key}"):
            table.delValue(f"{prefix}{key}")


def unread_options(prefix: str, options: dict[str, Any], factor: bool) -> dict[str, Any]:
    """Check the expert PETSc ``options`` set under ``prefix`` against what PETSc read.

    ``mat_*`` options are read by the factor at its first set-up (the first solve), the others
    by ``SNESSetFromOptions``. With ``factor`` False the others are checked and the ``mat_*``
    ones returned for a check after the first solve; with ``factor`` True all are checked.

    Raises:
        InputError: naming the options none of the SNES, KSP, PC and factor read.

    """
    table = PETSc.Options()
    due = {k: v for k, v in options.items() if factor or not k.startswith("mat_")}
    unread = {k: v for k, v in due.items() if not table.used(f"{prefix}{k}")}
    if unread:
        names = ", ".join(f"newton.options.petsc.{k} = {v!r}" for k, v in unread.items())
        raise InputError(f"{names}: not read by PETSc (a misspelt name, a value of the wrong "
                         "kind, or an option of a solver not in use)")
    return {k: v for k, v in options.items() if k not in due}


class EnergyNewton:
    """Minimise an energy form ``Pi(u)`` with SNES Newton and an energy line search.

    Args:
        energy: UFL scalar form ``Pi(u)`` (a functional of the Function ``u``).
        u: The unknown; holds the initial guess on entry to ``solve`` and the result after.
        bcs: Dirichlet conditions on ``u`` (their values must already be set in ``u``).
        det_f: UFL expression of ``det F(u)`` whose minimum over quadrature points defines
            admissibility (``energy = +inf`` where it is ``<= 0``).
        quadrature_degree: Degree of the points at which ``det_f`` is checked.
        options: Tolerances and line search switch.
        energy_scale: Magnitude of the terms summed into ``Pi`` [J], e.g.
            ``(mu + lambda) |Omega|``; sets the energy noise band of the line search.

    """

    def __init__(self, energy: Any, u: Any, bcs: list[Any], det_f: Any,
                 quadrature_degree: int, options: NewtonOptions | None = None,
                 energy_scale: float = 0.0) -> None:
        self.options = options or NewtonOptions()
        self.energy_scale = float(energy_scale)
        self.u = u
        mesh = u.function_space.mesh
        self._mesh = mesh
        self._det_f = quadrature_expression(det_f, mesh, quadrature_degree)
        residual = ufl.derivative(energy, u, ufl.TestFunction(u.function_space))
        jacobian = ufl.derivative(residual, u, ufl.TrialFunction(u.function_space))
        self._full = tuple(dolfinx.fem.form(f) for f in (energy, residual, jacobian))
        self._energy, self._F, self._J = self._full
        self._prefix = f"body_newton_{next(_COUNTER)}_"
        self.problem = dolfinx.fem.petsc.NonlinearProblem(
            self._F, u, bcs=bcs, J=self._J, petsc_options_prefix=self._prefix,
            kind=self.options.matrix_kind)
        self._unchecked = configure(self.problem.solver, self.options.petsc_options(),
                                    self.options.petsc)
        self.problem.solver.setObjective(self._objective)  # type: ignore[arg-type]
        if self.options.line_search and not self.options.uses_petsc_bt:
            self.problem.solver.setLineSearchPreCheck(self._armijo)
        self.problem.solver.setConvergenceTest(self._convergence_test)
        self._bcs, self._bc_rows = bcs, bc_rows(bcs, u)
        self._wrap_callbacks()
        self._term: QuadraticTerm | None = None
        self._term_jacobian: Any = None
        self._union: Any = None
        self.backtracks = 0
        self.flips = 0
        self._last_step, self._ls_failed, self._fnorm0 = 1.0, False, math.inf
        self.iterative: IterativeBodySolve | None = None
        self._choice_due = self.options.chooses_method
        if self.options.method == "iterative":
            self._use_iterative()

    @property
    def linear_method(self) -> str:
        """``"iterative"`` (CG + GAMG, :mod:`solvers.body_linear`) or ``"direct"`` (the LU)."""
        return "direct" if self.iterative is None else "iterative"

    def _use_iterative(self) -> None:
        """Solve the Newton steps from now on by CG + GAMG (the LU where CG fails).

        SNES gets a new ``preonly`` KSP around the ``PCPYTHON`` context; the one that held the
        LU goes with its factor.
        """
        snes = self.problem.solver
        self.iterative = IterativeBodySolve(self._prefix)
        ksp = PETSc.KSP().create(snes.getComm())
        ksp.setType(PETSc.KSP.Type.PREONLY)
        ksp.getPC().setType(PETSc.PC.Type.PYTHON)
        ksp.getPC().setPythonContext(self.iterative)
        snes.setKSP(ksp)
        ksp.destroy()  # SNES holds its reference

    def _choose_method(self) -> None:
        """After the first factorisation: CG + GAMG if it cost more than the crossover."""
        self._choice_due = False
        factor = self.problem.solver.getKSP().getPC().getFactorMatrix()
        if choose_body_method(float(factor.getMumpsRinfog(1))) == "iterative":
            self._use_iterative()

    def energy(self) -> float:
        """``Pi(u)`` at the current ``u`` [J], ``+inf`` if ``det F <= 0`` anywhere."""
        if self.min_det_f() <= 0.0:
            return math.inf
        value = global_scalar(self._energy)
        if self._term is not None:
            value += self._term.value(self.u.x.petsc_vec)
        return value if math.isfinite(value) else math.inf

    def set_quadratic_term(self, term: QuadraticTerm | None) -> None:
        """Add ``term`` to the energy, residual and Jacobian of later solves (``None``: remove).

        The first term set recreates the Jacobian matrix with the union of the form's and
        ``K``'s patterns (later terms must have a pattern inside it). Collective.
        """
        self._term = term
        if self._term_jacobian is not None:
            self._term_jacobian.destroy()
            self._term_jacobian = None
        if term is None:
            return
        self._term_jacobian = term.K.duplicate(copy=True)
        self._term_jacobian.zeroRowsColumns(self._bc_rows, diag=0.0)
        if self._union is None:
            A = self.problem.A
            self._assemble_jacobian(self.u.x.petsc_vec, A)  # the form's pattern, assembled
            self._union = A.convert("aij")  # K's pattern differs from the form's blocks
            self._union.axpy(1.0, self._term_jacobian,
                             structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
            self._union.setLGMap(*A.getLGMap())
            self.problem.solver.setJacobian(self._jacobian, self._union, self._union)

    @property
    def dirichlet_rows(self) -> np.ndarray:
        """Global PETSc indices of the Dirichlet dofs owned by this rank."""
        return self._bc_rows

    def gradient(self) -> Any:
        """``dPi/du`` at the current ``u``, quadratic term included (collective).

        Returns the solver's residual vector (owned rows; overwritten by the next call): the
        Dirichlet rows hold ``u - g``, zero when ``u`` satisfies the pins.
        """
        self._residual(None, self.u.x.petsc_vec, self.problem.b)
        return self.problem.b

    def hessian(self) -> Any:
        """``d^2 Pi/du^2`` at the current ``u`` with identity Dirichlet rows and columns.

        Returns the solver's Jacobian matrix (overwritten by the next call); collective.
        """
        J = self._union if self._union is not None else self.problem.A
        self._jacobian(None, self.u.x.petsc_vec, J, J)
        return J

    def _wrap_callbacks(self) -> None:
        """Replace dolfinx's SNES residual by :meth:`_residual` (dolfinx's assembly + term).

        The assembly is :func:`models.backend.assemble_snes_residual`: dolfinx's, without the
        lifting of Dirichlet values the iterate already meets.
        """
        snes, problem, bcs = self.problem.solver, self.problem, self._bcs
        work = problem.b.duplicate()
        self._assemble_residual = lambda x, b: assemble_snes_residual(
            x, b, self.u, self._F, self._J, bcs, work)
        self._assemble_jacobian = lambda x, J: dolfinx.fem.petsc.assemble_jacobian(
            snes, x, J, J, self.u, self._J, None, bcs)
        snes.setFunction(self._residual, self.problem.b)
        snes.setJacobian(self._jacobian, problem.A, problem.A)

    def set_facet_domains(self, domains: dict[int, Any] | None) -> None:
        """Integrate the exterior-facet subdomains in ``domains`` over the facets given there.

        The energy, residual and Jacobian of the coming solves integrate ``ds(i)`` over
        ``domains[i]`` (``(cell, local facet)`` pairs, :func:`models.backend.
        exterior_facet_domain`): the caller guarantees that the integrand vanishes on the
        facets left out (e.g. a contact penalty away from its obstacle). ``None`` restores
        the forms as compiled. :attr:`problem` keeps the compiled forms.
        """
        if domains is None:
            self._energy, self._F, self._J = self._full
            return
        self._energy, self._F, self._J = (with_facet_domains(f, domains) for f in self._full)

    def _residual(self, _snes: Any, x: Any, b: Any) -> None:
        """Residual of dolfinx plus ``K u - c`` on the free rows (SNES function)."""
        self._assemble_residual(x, b)
        if self._term is None:
            return
        g = self._term.gradient(x)
        g.setValues(self._bc_rows, np.zeros(self._bc_rows.size))
        g.assemble()
        b.axpy(1.0, g)
        g.destroy()
        b.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)

    def _jacobian(self, _snes: Any, x: Any, J: Any, _P: Any) -> None:
        """Jacobian of dolfinx plus ``K`` without Dirichlet rows / columns (SNES Jacobian)."""
        self._assemble_jacobian(x, J)
        if self._term_jacobian is not None:
            J.axpy(1.0, self._term_jacobian, structure=PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)

    def min_det_f(self) -> float:
        """Minimum of ``det F(u)`` over all quadrature points of all cells and ranks."""
        return global_min_on_cells(self._det_f, self._mesh)

    def det_f_points(self) -> np.ndarray:
        """``det F(u)`` at the quadrature points of this rank's owned cells, (cells, points).

        The expression behind :meth:`min_det_f`; non-finite values come back as ``-inf``.
        """
        n_local = self._mesh.topology.index_map(self._mesh.topology.dim).size_local
        values = self._det_f.eval(self._mesh, np.arange(n_local, dtype=np.int32))
        return np.where(np.isfinite(values), values, -np.inf).reshape(n_local, -1)

    def _objective(self, _snes: Any, x: Any) -> float:
        """SNES objective: copy ``x`` into ``u`` (with ghosts) and return ``Pi(u)``."""
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        dolfinx.fem.petsc.assign(x, self.u)
        return self.energy()

    def _armijo(self, x: Any, y: Any) -> None:
        """SNES pre-check: scale the step ``-y`` by the Armijo ``l`` (module doc); 0 on failure.

        SNES updates ``x <- x - y``, so the Newton step is ``du = -y`` and the directional
        derivative ``s = dPi.du = -r.y`` with ``r`` the residual at ``x``. Where the Jacobian
        is indefinite (strong compression) ``s`` can be > 0; the step is then reversed, which
        makes it a descent direction (counted in ``flips``).
        """
        opts, snes = self.options, self.problem.solver
        energy0 = self._objective(snes, x)
        noise = opts.energy_roundoff * (abs(energy0) + self.energy_scale)
        slope = -float(self.problem.b.dot(y).real)
        if slope > 0.0:  # indefinite Jacobian: -du is a descent direction, du is not
            y.scale(-1.0)
            slope, self.flips = -slope, self.flips + 1
        trial = x.duplicate()
        step = 1.0
        for _ in range(opts.max_backtracks):
            x.copy(trial)
            trial.axpy(-step, y)
            energy = self._objective(snes, trial)
            if energy <= energy0 + opts.armijo_c1 * step * min(slope, 0.0):
                break
            if abs(energy - energy0) <= noise and self._residual_decreases(trial):
                break
            step *= 0.5
            self.backtracks += 1
        else:
            step, self._ls_failed = 0.0, True
        trial.destroy()
        self._last_step = step
        y.scale(step)

    def _residual_decreases(self, trial: Any) -> bool:
        """Whether ``|r(trial)| < |r(x)|`` (``r(x)`` is SNES's current residual ``b``)."""
        residual = self.problem.b.duplicate()
        self.problem.solver.computeFunction(trial, residual)
        smaller = residual.norm() < self.problem.b.norm()  # type: ignore[operator]
        residual.destroy()
        return bool(smaller)

    def _convergence_test(self, _snes: Any, it: int, norms: tuple[float, float, float]) -> Any:
        """SNES convergence test: residual (abs/rel), or a small *full* Newton step.

        PETSc's default step test would also fire on a step shrunk by the line search.
        """
        xnorm, ynorm, fnorm = norms
        reason, opts = PETSc.SNES.ConvergedReason, self.options
        self._fnorm0 = fnorm if it == 0 else self._fnorm0
        if not math.isfinite(fnorm):
            return reason.DIVERGED_FUNCTION_NANORINF
        if self._ls_failed:
            return reason.DIVERGED_LINE_SEARCH
        if fnorm <= opts.atol:
            return reason.CONVERGED_FNORM_ABS
        if it > 0 and fnorm <= opts.rtol * self._fnorm0:
            return reason.CONVERGED_FNORM_RELATIVE
        full_step = self._last_step == 1.0 and not opts.uses_petsc_bt
        if it > 0 and full_step and ynorm <= opts.stol * xnorm:
            return reason.CONVERGED_SNORM_RELATIVE
        if it >= opts.max_it:
            return reason.DIVERGED_MAX_IT
        return reason.ITERATING

    def solve(self) -> NewtonResult:
        """Run SNES from the current ``u``; ``u`` holds the last iterate afterwards."""
        snes = self.problem.solver
        start = self.min_det_f()
        if not start > 0.0:
            return NewtonResult(False, 0, 0, math.nan, math.inf, start)
        self._last_step, self._ls_failed = 1.0, False
        self.problem.solve()
        if self._choice_due and snes.getIterationNumber() > 0:  # the first factorisation
            self._choose_method()
        if self._unchecked and snes.getIterationNumber() > 0:  # read at the factor's set-up
            try:
                self._unchecked = unread_options(self._prefix, self._unchecked, factor=True)
            except InputError:
                clear_options(self._prefix, self.options.petsc_options())
                raise
        reason = int(snes.getConvergedReason())  # type: ignore[call-overload]
        min_det = self.min_det_f()
        energy = self.energy()
        residual = float(snes.getFunctionNorm())
        converged = reason > 0 and min_det > 0.0 and math.isfinite(energy) and bool(
            np.isfinite(residual))
        return NewtonResult(converged, reason, int(snes.getIterationNumber()), residual,
                            energy, min_det)
