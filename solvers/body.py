"""The coarse hyperelastic body: one UFL energy, statics and implicit dynamics, pins, contact.

Every step minimises one incremental potential (Ortiz & Stainier 1999; Kane et al. 2000)

    Pi(u) = int_Omega psi(F(u)) dX                                   (materials.py)
          + int_Omega rho c / 2 |u - u_pred|^2 dX                    (inertia, dynamics only)
          - int_Omega rho g.u dX - F.u                               (gravity, nodal load)
          + sum_obstacles int_dOmega k/2 <g(X + u)>_-^2 dA           (contact.py)

with, for a step of length h from (u_n, v_n, a_n):
    implicit Euler:  c = 1/h^2,       u_pred = u_n + h v_n;                v = (u - u_n)/h
    Newmark (beta = 1/4, gamma = 1/2, average acceleration):
                     c = 1/(beta h^2), u_pred = u_n + h v_n + h^2 (1/2 - beta) a_n,
                     a = c (u - u_pred),  v = v_n + h ((1 - gamma) a_n + gamma a).
The stationarity of Pi is the time-discrete momentum balance, so the residual and the
Jacobian are ``ufl.derivative`` of Pi and the Newton line search can evaluate Pi itself.

The nodal load ``F`` (zero unless :meth:`Body.set_nodal_load` sets it, e.g. a given force
field ``B^T f`` on the embedded shell's points, :mod:`models.coupling`) is written in UFL
as ``-int g.u dX`` with ``g`` the L2 Riesz representative of ``F`` (``M g = F``, M the vector
mass matrix with the energy's quadrature, exact for P1 and P2), so its first variation is
exactly ``-F``; it is part of the ``gravity`` (external load) energy term.

Pins (``PinSpec``) hold selected components of selected nodes at
``(R(angle + omega t) - I)(X - center) + value + velocity * t`` (``R`` the rotation about
``axis``): a moving pin compresses, stretches, twists or bends the body over time. In
statics, ``t`` is the load parameter and a step advances it by ``dt``. A failed step is
retried with half the step (time step or load increment), ``NewtonOptions.max_halvings``
times, from the last good state; then ``SolverError`` is raised with that state restored.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from meshes.errors import InputError, SolverError
from models.backend import (
    MPI,
    PETSc,
    dolfinx,
    exterior_facet_domain,
    global_scalar,
    is_affine,
    ufl,
    vector_space,
    with_facet_domains,
)
from models.body import (
    NEWMARK_BETA,
    NEWMARK_GAMMA,
    BodyOptions,
    PinSpec,
    pin_conflicts,
    refuse_empty_pins,
    refuse_pin_conflicts,
)
from models.contact import PenaltyContact, exterior_facets, min_cell_size, penalty_stiffness
from models.materials import Material
from models.quadratic import QuadraticTerm
from solvers.body_newton import EnergyNewton, NewtonOptions, NewtonResult
from solvers.contact_set import ActiveFacets, ContactSetStats


class _PinValue:
    """Prescribed values of component ``k`` of one pin and their Dirichlet condition.

    A translating pin has one value for all its nodes (a ``Constant``); a rotating pin has one
    per node, held in a ``Function`` on the collapsed component space ``V.sub(k)``.

    Args:
        mesh: The body's mesh.
        V: The body's vector space.
        pin: The pin.
        k: Component held.
        dofs: Dofs ``3 i + k`` of the pinned nodes ``i`` in ``V``.
        X: Reference positions of the pinned nodes, (n, 3) [m].

    """

    def __init__(self, mesh: Any, V: Any, pin: PinSpec, k: int, dofs: np.ndarray,
                 X: np.ndarray) -> None:
        self.pin, self.k, self.X = pin, k, X
        self.value: Any
        self.cdofs: np.ndarray | None = None
        if not pin.rotates:
            self.value = dolfinx.fem.Constant(mesh, float(pin.displacement(0.0)[k]))
            self.bc = dolfinx.fem.dirichletbc(self.value, dofs, V.sub(k))
            return
        Vk, parent = V.sub(k).collapse()
        parent = np.asarray(parent).reshape(-1)
        inverse = np.full(int(parent.max(initial=0)) + 1, -1, dtype=np.int32)
        inverse[parent] = np.arange(parent.size, dtype=np.int32)
        self.cdofs = inverse[dofs]
        self.value = dolfinx.fem.Function(Vk, name=f"pin_component_{k}")
        self.bc = dolfinx.fem.dirichletbc(self.value, np.vstack([dofs, self.cdofs]), V.sub(k))
        self.set(0.0)

    def set(self, t: float) -> None:
        """Set the prescribed values at time (load parameter) ``t``."""
        if self.cdofs is None:
            self.value.value = float(self.pin.displacement(t)[self.k])
            return
        self.value.x.array[self.cdofs] = self.pin.displacement_at(self.X, t)[:, self.k]


@dataclass(frozen=True)
class StepReport:
    """What one ``Body.step`` (or ``solve_static``) did.

    Attributes:
        time: Time (load parameter) reached [s].
        newton_iterations: Newton iterations summed over all attempts and sub-steps.
        energy: Total energy kinetic + elastic + gravity + contact [J].
        kinetic: Kinetic energy ``int rho/2 |v|^2`` [J].
        elastic: Stored energy ``int psi`` [J].
        gravity: Gravity potential ``-int rho g.u`` [J].
        contact: Penalty energy [J].
        min_det_f: Minimum ``det F`` over quadrature points [-].
        halvings: How many times the step was halved.
        substeps: Sub-steps taken to reach ``time``.
        converged: Always True for a returned report (failure raises ``SolverError``).

    """

    time: float
    newton_iterations: int
    energy: float
    kinetic: float
    elastic: float
    gravity: float
    contact: float
    min_det_f: float
    halvings: int
    substeps: int
    converged: bool = True


@dataclass
class _State:
    """Copies of the body's arrays and time, to restore after a failed step."""

    t: float
    arrays: list[np.ndarray] = field(default_factory=list)


class Body:
    """A hyperelastic body on a dolfinx tetrahedral mesh.

    Args:
        mesh: dolfinx tetrahedral mesh (reference configuration, SI units).
        material: Its material.
        options: Discretisation, dynamics, loads and pins.
        newton: Newton solver options.

    Attributes:
        u: Displacement (dolfinx Function on the vector P1/P2 space ``V``) [m].
        v: Velocity [m/s].
        a: Acceleration [m/s^2] (Newmark only; zero otherwise).
        t: Current time (load parameter) [s].
        contacts: ``PenaltyContact`` objects, one per ``options.contacts`` entry.
        load: nodal load density ``g`` [N/m^3] with ``M g = F`` (:meth:`set_nodal_load`).

    """

    def __init__(self, mesh: Any, material: Material, options: BodyOptions | None = None,
                 newton: NewtonOptions | None = None) -> None:
        self.mesh, self.material = mesh, material
        self.options = options or BodyOptions()
        self.newton = newton or NewtonOptions()
        self.V = vector_space(mesh, self.options.degree)
        self.u, self.v, self.a = (self._function(n) for n in ("displacement", "velocity",
                                                              "acceleration"))
        self._u_n, self._v_n, self._a_n, self._u_pred = (self._function(n) for n in
                                                          ("u_n", "v_n", "a_n", "u_pred"))
        self.t = 0.0
        self.rate = self._function("load_rate")  # du/dt of the last static step
        self._accel_ready = False
        self._inertia = dolfinx.fem.Constant(mesh, 0.0)
        self.gravity = dolfinx.fem.Constant(mesh, np.array(self.options.gravity))
        self.load = self._function("nodal_load_density")
        self._load_forms: list[Any] | None = None
        self._inertia_force: Any = None  # int rho a.w dX (pin_reaction, Newmark)
        self._mass_ksp: Any = None
        self._compliance_ksp: Any = None  # obstacle_compliance
        self._coupling_forms: dict[int, list[Any]] = {}
        self._term: QuadraticTerm | None = None
        self._solve: Callable[[EnergyNewton], NewtonResult] = EnergyNewton.solve
        self._interface: Any = None  # set_interface_force
        k = (penalty_stiffness(self.options.contact_stiffness, material.E, min_cell_size(mesh))
             if self.options.contacts else 0.0)
        facets, self._facets = None, exterior_facets(mesh)
        self._facet_pairs = exterior_facet_domain(mesh, self._facets)
        if self.options.contacts:
            facets = [(i, self._facet_pairs) for i in range(len(self.options.contacts))]
        self.contacts = [PenaltyContact(c, mesh, k, i, facets)
                         for i, c in enumerate(self.options.contacts)]
        self.dx = ufl.Measure("dx", domain=mesh,
                              metadata={"quadrature_degree": self.options.qdegree})
        self._dx_elastic = ufl.Measure(
            "dx", domain=mesh,
            metadata={"quadrature_degree": self.options.elastic_qdegree(is_affine(mesh))})
        self._bcs, self._pin_constants = self._build_pins()
        self._compile_forms()

    # --- construction ------------------------------------------------------------------------

    def _function(self, name: str) -> Any:
        return dolfinx.fem.Function(self.V, name=name)

    def _build_pins(self) -> tuple[list[Any], list[tuple[PinSpec, int, Any, np.ndarray]]]:
        """One Dirichlet condition per (pin, component) on the nodes it selects.

        The dof of node ``i`` (``V.tabulate_dof_coordinates()`` row, owned and ghost, P1 or
        P2 nodes) and component ``k`` in the blocked space is ``3 i + k``.
        """
        X = self.V.tabulate_dof_coordinates()
        owned = self.V.dofmap.index_map.size_local
        self._refuse_conflicts(X, owned)
        bcs, constants = [], []
        selected = [np.flatnonzero(pin.select(X)).astype(np.int32) for pin in self.options.pins]
        self.pin_nodes: list[int] = [
            int(self.mesh.comm.allreduce(int(np.count_nonzero(nodes < owned)), op=MPI.SUM))
            for nodes in selected]
        if 0 in self.pin_nodes:  # the same counts on every rank: all of them gather the span
            span = [np.full(3, np.inf), np.full(3, -np.inf)]
            self.mesh.comm.Allreduce(X[:owned].min(axis=0, initial=np.inf), span[0], op=MPI.MIN)
            self.mesh.comm.Allreduce(X[:owned].max(axis=0, initial=-np.inf), span[1],
                                     op=MPI.MAX)
            refuse_empty_pins(self.options.pins, self.pin_nodes, (span[0], span[1]))
        for pin, nodes in zip(self.options.pins, selected, strict=True):
            for k in pin.components:
                dofs = (3 * nodes + k).astype(np.int32)
                value = _PinValue(self.mesh, self.V, pin, k, dofs, X[nodes])
                bcs.append(value.bc)
                constants.append((pin, k, value, dofs))
        return bcs, constants

    def _refuse_conflicts(self, X: np.ndarray, owned: int) -> None:
        """Raise InputError on every rank if two pins move a shared node differently.

        :func:`models.body.pin_conflicts` on this rank's owned nodes; the first conflict of
        the lowest rank that has one is named.
        """
        found = [(c.first, c.second, c.component, X[c.nodes])
                 for c in pin_conflicts(self.options.pins, X[:owned])]
        everywhere = self.mesh.comm.allgather(found)
        refuse_pin_conflicts([c for rank in everywhere for c in rank],
                             self.mesh.comm.allreduce(float(np.abs(X).max(initial=0.0)),
                                                      op=MPI.MAX))

    def deformation_gradient(self, u: Any | None = None) -> Any:
        """``F = I + grad u`` (UFL)."""
        return ufl.Identity(3) + ufl.grad(self.u if u is None else u)

    def _energy_terms(self) -> dict[str, Any]:
        """UFL forms of the energy terms of the current state ``u``, ``v``."""
        rho, u, dx = self.material.density, self.u, self.dx
        terms = {
            "elastic": self.material.psi(self.deformation_gradient()) * self._dx_elastic,
            "gravity": -(rho * ufl.dot(self.gravity, u) + ufl.dot(self.load, u)) * dx,
            "kinetic": 0.5 * rho * ufl.dot(self.v, self.v) * dx,
            "contact": sum((c.energy(u) for c in self.contacts),
                           0.0 * ufl.dot(u, u) * dx),
        }
        return terms

    def _compile_forms(self) -> None:
        """Compile the energy terms, the static and dynamic potentials and their solvers."""
        terms = self._energy_terms()
        self._forms = {k: dolfinx.fem.form(v) for k, v in terms.items()}
        static = terms["elastic"] + terms["gravity"] + terms["contact"]
        diff = self.u - self._u_pred
        inertia = 0.5 * self.material.density * self._inertia * ufl.dot(diff, diff) * self.dx
        detf = ufl.det(self.deformation_gradient())
        q, scale = self.options.qdegree, self._energy_scale()
        self._static_solver = EnergyNewton(static, self.u, self._bcs, detf, q, self.newton,
                                           scale)
        self._dynamic_solver = (None if self.options.dynamics == "static" else
                                EnergyNewton(static + inertia, self.u, self._bcs, detf, q,
                                             self.newton, scale))
        self._reaction = [[dolfinx.fem.form(f) for f in c.force_forms(self.u)]
                          for c in self.contacts]
        self._active = (ActiveFacets(self.mesh, self.V, self.contacts, self._facets,
                                     self._facet_pairs, self._forms["contact"])
                        if self.contacts else None)
        self._static_ufl = static

    def _energy_scale(self) -> float:
        """Magnitude ``(mu + lambda) |Omega|`` [J] of the summed energy terms (noise band)."""
        volume = global_scalar(dolfinx.fem.form(1.0 * self.dx))
        return (self.material.mu + self.material.lmbda) * volume

    # --- public API --------------------------------------------------------------------------

    def energies(self) -> dict[str, float]:
        """Kinetic, elastic, gravity, contact and total energy of the current state [J]."""
        values = {k: global_scalar(f) for k, f in self._forms.items()}
        if self._term is not None:
            values["gravity"] += self._term.value(self.u.x.petsc_vec)
        values["total"] = sum(values.values())
        return values

    def min_det_f(self) -> float:
        """Minimum of ``det F`` over all volume quadrature points (all ranks) [-]."""
        return self._static_solver.min_det_f()

    def det_f_points(self) -> np.ndarray:
        """``det F = det(I + grad u)`` at the volume quadrature points of each owned cell [-].

        Evaluates the expression behind :meth:`min_det_f` (compiled once, by the static
        solver). Non-finite values are returned as ``-inf``, never mistaken for an admissible
        state. Shape ``(owned cells, quadrature points)``.
        """
        return self._static_solver.det_f_points()

    def reaction_force(self, index: int = 0) -> np.ndarray:
        """Force exerted by obstacle ``index`` on the body [N] (the obstacle feels minus it).

        ``R = int_dOmega -k <g>_- grad g dA`` assembled at the current displacement.
        """
        if not 0 <= index < len(self._reaction):
            raise InputError(f"reaction_force: no contact number {index} "
                             f"({len(self._reaction)} defined)")
        return np.array([global_scalar(f) for f in self._reaction[index]])

    def contact_domains(self) -> dict[int, Any] | None:
        """Each obstacle's facets that carry its penalty at the current ``u`` (collective).

        :meth:`solvers.contact_set.ActiveFacets.at`: forms of the obstacles' penalties
        integrated over these facets (:func:`models.backend.with_facet_domains`) equal the
        forms over all exterior facets. None: integrate over all (no obstacle, or a facet
        left out is penetrated).
        """
        return None if self._active is None else self._active.at(self.u.x.array)

    def obstacle_compliance(self, indices: list[int],
                            domains: dict[int, Any] | None = None) -> np.ndarray:
        """``S = G^T A^{-1} G`` [N/m] of the sphere obstacles ``indices``, (3N, 3N) (collective).

        ``A`` is the Jacobian of the step's potential (the dynamic one when the body moves)
        at the current ``u``, with identity rows and columns at the pins; ``G`` holds the
        columns :meth:`models.contact.PenaltyContact.center_coupling_forms` of each obstacle,
        zero at the pins. Moving sphere ``j`` by ``dc`` moves the body in equilibrium by
        ``A^{-1} G_j dc``, so ``K_c - S`` is the stiffness of the spheres against the
        compliant body, ``dR/dc`` (Schur complement of ``A`` in the Hessian of body and
        spheres together). One factorisation and ``3N`` solves. ``domains``
        (:meth:`contact_domains` at the current ``u``) integrates the obstacles' terms of ``A``
        and ``G`` over the facets that carry them, the same sums.
        """
        solver = self._dynamic_solver or self._static_solver
        solver.set_facet_domains(domains)
        try:
            A = solver.hessian()
        finally:
            solver.set_facet_domains(None)
        if self._compliance_ksp is None:
            self._compliance_ksp = PETSc.KSP().create(self.mesh.comm)
            self._compliance_ksp.setType("preonly")
            self._compliance_ksp.getPC().setType("lu")
            self._compliance_ksp.getPC().setFactorSolverType(self.newton.linear_solver)
        ksp = self._compliance_ksp
        ksp.setOperators(A)
        rows, columns = solver.dirichlet_rows, []
        for i in indices:
            if i not in self._coupling_forms:
                w = ufl.TestFunction(self.V)
                self._coupling_forms[i] = [dolfinx.fem.form(f) for f in
                                           self.contacts[i].center_coupling_forms(self.u, w)]
            for form in self._coupling_forms[i]:
                if domains is not None:
                    form = with_facet_domains(form, domains)
                g: Any = dolfinx.fem.petsc.assemble_vector(form)
                g.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
                g.setValues(rows, np.zeros(rows.size))
                g.assemble()
                columns.append(g)
        solved = [g.duplicate() for g in columns]
        for g, x in zip(columns, solved, strict=True):
            ksp.solve(g, x)
        S = np.array([[gi.dot(xj).real for xj in solved] for gi in columns])
        for v in (*columns, *solved):
            v.destroy()
        return 0.5 * (S + S.T)

    def set_nodal_load(self, F: Any) -> None:
        """Make the nodal force ``F`` (dolfinx Function on ``V``) a load: ``Pi -= F . u``.

        Solves ``M g = F`` for the load density :attr:`load` (collective); the next steps and
        :meth:`energies` include ``-int g . u dX``. A zero ``F`` removes the load.
        """
        self._mass_solver().solve(F.x.petsc_vec, self.load.x.petsc_vec)
        self.load.x.scatter_forward()

    def set_quadratic_energy(self, term: QuadraticTerm | None) -> None:
        """Add a quadratic energy to the potential of later steps (``None``: remove it).

        The term ``1/2 u^T K u - c^T u + e0`` (:class:`solvers.body_newton.QuadraticTerm`)
        also counts in the ``gravity`` (external) entry of :meth:`energies`. Collective.

        Two-way coupling makes the shell's cluster penalty, with the shell fixed, such a term
        (:func:`models.coupling.penalty_term`): an implicit load that the body's Newton
        solves together with its own energy.
        """
        self._term = term
        for solver in (self._static_solver, self._dynamic_solver):
            if solver is not None:
                solver.set_quadratic_term(term)

    def linear_facts(self) -> dict[str, Any]:
        """How the Newton systems of the body's steps are solved (:mod:`solvers.body_linear`).

        ``method`` (``"direct"`` or ``"iterative"``); for the latter the CG solves, their
        iterations and the steps the LU solved where CG failed, over this process's run.
        """
        solver = self._dynamic_solver or self._static_solver
        facts: dict[str, Any] = {"method": solver.linear_method}
        if solver.iterative is not None:
            facts.update(cg_solves=solver.iterative.solves,
                         cg_iterations=solver.iterative.cg_iterations,
                         lu_fallbacks=solver.iterative.fallbacks)
        return facts

    def set_interface_force(self, F: Any | None) -> None:
        """Record the nodal force ``F`` (Function on ``V``) another model exerts outside ``Pi``.

        The monolithic two-way shell (:mod:`solvers.monolithic`) minimises ``Pi`` together
        with the shell energy, so the shell's force ``B^T f`` on the body is in no form of
        ``Pi``; on pinned nodes the pins carry it, and :meth:`pin_reaction` subtracts it there
        (``None``: no such force).
        """
        self._interface = F

    def use_solve(self, solve: Callable[[EnergyNewton], NewtonResult] | None) -> None:
        """Replace the Newton solve of every (sub)step by ``solve(problem)`` (``None``: restore).

        ``problem`` is the step's :class:`EnergyNewton` (``Pi`` with the step's pins, inertia
        and guess already set in ``u``); ``solve`` must leave ``u`` at its solution and report
        it, like :meth:`EnergyNewton.solve`. The two-way coupled solve
        (:mod:`solvers.monolithic`) minimises ``Pi`` together with the shell energy this way,
        inside the body's own step control (halvings, dynamics, rigid balls).
        """
        self._solve = EnergyNewton.solve if solve is None else solve

    def applied_load(self) -> np.ndarray:
        """Total force ``int g dX`` [N] of the nodal load (3,); equals ``sum_j F_j``."""
        if self._load_forms is None:
            self._load_forms = [dolfinx.fem.form(self.load[k] * self.dx) for k in range(3)]
        return np.array([global_scalar(form) for form in self._load_forms])

    def _mass_solver(self) -> Any:
        """LU solver of the vector mass matrix (built once, same quadrature as the energy)."""
        if self._mass_ksp is None:
            w, du = ufl.TestFunction(self.V), ufl.TrialFunction(self.V)
            M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.dot(du, w) * self.dx))
            M.assemble()
            ksp = PETSc.KSP().create(self.mesh.comm)
            ksp.setOperators(M)
            ksp.setType("preonly")
            ksp.getPC().setType("lu")
            ksp.getPC().setFactorSolverType(self.newton.linear_solver)
            self._mass_ksp, self._mass = ksp, M
        return self._mass_ksp

    def set_sphere_center(self, center: Any, index: int = 0) -> None:
        """Move the centre of sphere obstacle ``index`` [m] before the next step."""
        self.contacts[index].set_center(center)

    def pin_reaction(self) -> np.ndarray:
        """Total force of the pins on the body [N], (3,), at the current state (collective).

        At a pinned dof the pin supplies the force that makes the potential stationary: the
        residual ``dPi/du`` there (assembled without Dirichlet rows, the last step's
        potential: with inertia in dynamics; Newmark: static residual + ``M a``, also right
        at t = 0 once ``a_0`` is set), summed per component over the owned pinned dofs. The
        quadratic term of :meth:`set_quadratic_energy` is not included; the force of
        :meth:`set_interface_force` is (the pins carry its share on pinned nodes).
        """
        solver = self._dynamic_solver or self._static_solver
        forms = [solver.problem.F]
        if self.options.dynamics == "newmark":
            if self._inertia_force is None:
                w = ufl.TestFunction(self.V)
                self._inertia_force = dolfinx.fem.form(
                    self.material.density * ufl.dot(self.a, w) * self.dx)
            forms = [self._static_solver.problem.F, self._inertia_force]
        b = dolfinx.fem.assemble_vector(forms[0])
        for form in forms[1:]:
            b.array[:] += dolfinx.fem.assemble_vector(form).array
        b.scatter_reverse(dolfinx.la.InsertMode.add)
        dofs = np.unique(np.concatenate([bc.dof_indices()[0][:bc.dof_indices()[1]]
                                         for bc in self._bcs] or [np.zeros(0, np.int32)]))
        values = b.array[dofs]
        if self._interface is not None:
            values = values - self._interface.x.array[dofs]
        force = np.zeros(3)
        np.add.at(force, dofs % 3, values)
        return np.asarray(self.mesh.comm.allreduce(force, op=MPI.SUM))

    def initial_acceleration(self) -> None:
        """Newmark: compute ``a_0`` now if it is not valid yet.

        Call before taking a snapshot that later steps restore (the rigid-ball coupling).
        """
        self._ensure_initial_acceleration()

    def set_state(self, t: float, u: np.ndarray, v: np.ndarray, a: np.ndarray,
                  rate: np.ndarray | None = None) -> None:
        """Set time and state (e.g. from a checkpoint) and mark the acceleration as valid.

        Newmark (beta = 1/4, gamma = 1/2) needs ``a_n`` consistent with ``(u_n, v_n)``: a
        restored ``a`` is used as is instead of being recomputed from ``M a_0 = -dPi/du``, so
        a restarted run continues exactly like the uninterrupted one; so does a static run
        given the load ``rate`` of its last step (the next step's guess ``u + h rate``).

        Args:
            t: Time (load parameter) of the state [s].
            u: Displacement dof values (local array incl. ghosts, layout of ``u.x.array``) [m].
            v: Velocity dof values [m/s].
            a: Acceleration dof values [m/s^2].
            rate: ``du/dt`` of the last static step [m/s] (``None``: zero).

        Raises:
            InputError: an array of the wrong size or with NaN/inf values, or ``t`` not finite.

        """
        if not math.isfinite(t):
            raise InputError(f"set_state: t must be finite, got {t}")
        rate = np.zeros_like(self.rate.x.array) if rate is None else rate
        for name, f, values in (("u", self.u, u), ("v", self.v, v), ("a", self.a, a),
                                ("rate", self.rate, rate)):
            arr = np.asarray(values, dtype=float).reshape(-1)
            if arr.shape != f.x.array.shape or not np.all(np.isfinite(arr)):
                raise InputError(f"set_state: {name} must be {f.x.array.size} finite values")
            f.x.array[:] = arr
            f.x.scatter_forward()
        self.t = float(t)
        self._set_pins(self.t)
        self._accel_ready = True

    def step(self, guess: np.ndarray | None = None, dt: float | None = None,
             max_halvings: int | None = None) -> StepReport:
        """Advance by ``dt`` (time or load parameter), halving on failure.

        Args:
            guess: Initial Newton guess of ``u`` (this rank's dof array, pins applied on top)
                for the whole step; None: the predictor (dynamics) or ``u + h du/dt``
                (statics). A halved sub-step always starts from its predictor.
            dt: Step size; None: ``options.dt``.
            max_halvings: Halvings allowed; None: ``newton.max_halvings`` (0: a caller that
                halves the step itself, e.g. together with rigid balls).

        Raises:
            SolverError: The step failed ``max_halvings + 1`` times; the state before the
                step is restored.

        """
        dynamic = self.options.dynamics != "static"
        h = self.options.dt if dt is None else dt
        return self._advance(self.t + h, dynamic, guess, max_halvings)

    def solve_static(self) -> StepReport:
        """Equilibrium at the current time with the current pins (no inertia); v = 0."""
        report = self._advance(self.t, dynamic=False)
        for f in (self.v, self.a):
            f.x.array[:] = 0.0
        self._accel_ready = False  # Newmark recomputes a consistent a_0 at its next step
        return report

    # --- stepping ------------------------------------------------------------------------------

    def _advance(self, t_target: float, dynamic: bool, guess: np.ndarray | None = None,
                 max_halvings: int | None = None) -> StepReport:
        """Reach ``t_target`` by sub-steps, halving the sub-step after each failure.

        ``guess`` is the first sub-step's initial guess when that sub-step is the whole step;
        ``max_halvings`` None: ``newton.max_halvings``.
        """
        limit = self.newton.max_halvings if max_halvings is None else max_halvings
        start = self.snapshot()
        h = max(t_target - self.t, 0.0)
        iterations, halvings, substeps = 0, 0, 0
        first = True
        while first or self.t < t_target - 1e-12 * max(self.options.dt, abs(t_target)):
            first = False
            h = min(h, t_target - self.t)
            saved = self.snapshot()
            whole = guess is not None and halvings == 0 and substeps == 0
            result = self._substep(h, dynamic, guess if whole else None)
            iterations += result.iterations
            if result.converged:
                substeps += 1
                continue
            self.restore(saved)
            halvings += 1
            if halvings > limit or h == 0.0:
                self.restore(start)
                raise SolverError(self._diagnostic(result, halvings - 1, h))
            h *= 0.5
        return self._report(iterations, halvings, substeps)

    def _substep(self, h: float, dynamic: bool, guess: np.ndarray | None = None
                 ) -> NewtonResult:
        """One Newton solve from ``t`` to ``t + h`` (from ``guess`` if given); updates v, a, t."""
        t_new = self.t + h
        self._set_pins(t_new)
        solver = self._static_solver
        if dynamic:
            self._ensure_initial_acceleration()
            self._predict(h, guess)
            solver = self._dynamic_solver  # type: ignore[assignment]
        else:
            self._static_guess(h, guess)
        result = self._solve_on_facets(solver)
        if result.converged:
            if dynamic:
                self._update_kinematics(h)
            elif h > 0.0:
                self.rate.x.array[:] = (self.u.x.array - self._u_n.x.array) / h
            self.t = t_new
        return result

    def _solve_on_facets(self, solver: EnergyNewton) -> NewtonResult:
        """Solve with each obstacle's penalty on its candidate facets (:mod:`solvers.contact_set`).

        The solve starts from the current ``u`` (the guess, set after ``u_n``). If it fails or
        a facet left out is penetrated at its end, it is repeated from the same ``u`` with
        the penalties over all exterior facets (a solve installed by :meth:`use_solve` that
        moved its own state, e.g. the coupled shell, repeats from there).
        """
        if self._active is None:
            return self._solve(solver)
        start = self.u.x.array.copy()
        solver.set_facet_domains(self._active.select(start, self._u_n.x.array))
        try:
            result = self._solve(solver)
            passed = result.converged and self._active.outside() == 0.0
        finally:
            solver.set_facet_domains(None)
        if passed:
            return result
        self._active.stats.retries += 1
        self.u.x.array[:] = start
        return self._solve(solver)

    @property
    def contact_set(self) -> ContactSetStats | None:
        """Counters of the contact facet selection (None without obstacles)."""
        return None if self._active is None else self._active.stats

    def _static_guess(self, h: float, guess: np.ndarray | None = None) -> None:
        """Set the initial guess of a load step: ``u + h du/dt`` of the last step, pins applied.

        Falls back to the current ``u`` with the new pin values when the extrapolation
        is inadmissible (``det F <= 0``); a first step uses that directly. ``guess`` replaces
        the extrapolation.
        """
        self._u_n.x.array[:] = self.u.x.array
        self._set_guess(self.u.x.array + h * self.rate.x.array if guess is None else guess)

    def _set_guess(self, guess: np.ndarray) -> None:
        """Set ``u = guess`` with the pins applied; ``u_n`` (pins applied) if ``det F <= 0``."""
        self.u.x.array[:] = guess
        self._apply_bcs()
        if self._static_solver.min_det_f() <= 0.0:
            self.u.x.array[:] = self._u_n.x.array
            self._apply_bcs()

    def _set_pins(self, t: float) -> None:
        for _, _, value, _ in self._pin_constants:
            value.set(t)

    def _apply_bcs(self) -> None:
        for bc in self._bcs:
            bc.set(self.u.x.array)
        self.u.x.scatter_forward()

    def _predict(self, h: float, guess: np.ndarray | None = None) -> None:
        """Store u_n, v_n, a_n; set u_pred, the inertia weight and the guess (u_pred if None)."""
        newmark = self.options.dynamics == "newmark"
        beta = NEWMARK_BETA if newmark else 1.0
        for dst, src in ((self._u_n, self.u), (self._v_n, self.v), (self._a_n, self.a)):
            dst.x.array[:] = src.x.array
        pred = np.asarray(self.u.x.array + h * self.v.x.array)
        if newmark:
            pred += h * h * (0.5 - beta) * self.a.x.array
        self._u_pred.x.array[:] = pred
        self._inertia.value = 1.0 / (beta * h * h)  # type: ignore[assignment]
        self._set_guess(pred if guess is None else guess)

    def _update_kinematics(self, h: float) -> None:
        """Set v (and a for Newmark) at the end of the sub-step from the new u."""
        u, u_n, v_n, a_n = (f.x.array for f in (self.u, self._u_n, self._v_n, self._a_n))
        if self.options.dynamics == "newmark":
            a_new = (u - self._u_pred.x.array) / (NEWMARK_BETA * h * h)
            self.v.x.array[:] = v_n + h * ((1.0 - NEWMARK_GAMMA) * a_n + NEWMARK_GAMMA * a_new)
            self.a.x.array[:] = a_new
        else:
            self.v.x.array[:] = (u - u_n) / h

    def _ensure_initial_acceleration(self) -> None:
        """Newmark needs a_0: solve ``M a_0 = -dPi_static/du`` once (a_0 = 0 on pins)."""
        if self._accel_ready or self.options.dynamics != "newmark":
            return
        w, da = ufl.TestFunction(self.V), ufl.TrialFunction(self.V)
        mass = self.material.density * ufl.dot(da, w) * self.dx
        rhs = -ufl.derivative(self._static_ufl, self.u, w)
        zero = [dolfinx.fem.dirichletbc(dolfinx.fem.Constant(self.mesh, 0.0), dofs,
                                        self.V.sub(k))
                for _, k, _, dofs in self._pin_constants]
        problem = dolfinx.fem.petsc.LinearProblem(
            mass, rhs, bcs=zero, petsc_options_prefix=f"body_accel_{id(self)}_",
            petsc_options={"ksp_type": "preonly", "pc_type": "lu",
                           "pc_factor_mat_solver_type": self.newton.linear_solver})
        self.a.x.array[:] = problem.solve().x.array  # type: ignore[union-attr]
        self._accel_ready = True

    def _arrays(self) -> list[np.ndarray]:
        """Return the state arrays (views) that a failed step must restore."""
        fields = (self.u, self.v, self.a, self._u_n, self._v_n, self._a_n, self._u_pred)
        return [f.x.array for f in (*fields, self.rate)]

    def snapshot(self) -> _State:
        """Copy of the state arrays and time (to retry a step, or redo it with another load)."""
        return _State(self.t, [a.copy() for a in self._arrays()])

    def restore(self, state: _State) -> None:
        """Return to a :meth:`snapshot` (state arrays, time and pins; the load is kept)."""
        for array, saved in zip(self._arrays(), state.arrays, strict=True):
            array[:] = saved
        self.t = state.t
        self._set_pins(self.t)

    def _report(self, iterations: int, halvings: int, substeps: int) -> StepReport:
        e = self.energies()
        return StepReport(time=self.t, newton_iterations=iterations, energy=e["total"],
                          kinetic=e["kinetic"], elastic=e["elastic"], gravity=e["gravity"],
                          contact=e["contact"], min_det_f=self.min_det_f(),
                          halvings=halvings, substeps=substeps)

    def _diagnostic(self, result: NewtonResult, halvings: int, h: float) -> str:
        o = self.options
        return (f"body step failed at t={self.t:.6g} after {halvings} halvings "
                f"(last sub-step {h:.3e}, dt={o.dt:.3e}, dynamics={o.dynamics}, "
                f"degree={o.degree}, E={self.material.E:.3e}, nu={self.material.nu}, "
                f"model={self.material.model}): {result.describe()}; "
                f"state at t={self.t:.6g} restored")
