"""A fine volumetric bilayer in plane strain: a stiff film on a soft substrate, wrinkling.

The reference against which the embedded shell's wrinkles are validated (MISSION.md
section 9). The domain ``[0, L] x [0, H + h]`` holds a substrate of depth ``H``
(``E_s, nu_s``) under a film of thickness ``h`` (``E_f, nu_f``), both compressible
Neo-Hookean (:mod:`models.materials`) in plane strain: the 2-D deformation gradient is
embedded as ``F = [[F2, 0], [0, 1]]`` so the 3-D stored energy is reused unchanged. The
total energy ``Pi(u) = int chi_f psi_f(F) + (1 - chi_f) psi_s(F) dX`` (``chi_f`` the film's
indicator) is minimised by :class:`solvers.body_newton.EnergyNewton` (SNES Newton with the
energy line search, ``+inf`` where ``det F <= 0``).

Loading: lateral compression by load steps. ``u_x = 0`` on ``x = 0``, ``u_x = -eps L`` on
``x = L`` (both edges slide freely in y), ``u_y = 0`` on the bottom ``y = 0``; the top is free.
At the critical strain (Allen 1969; Chen & Hutchinson 2004; Huang, Hong & Suo 2005)

    eps_c = 1/4 (3 Ebar_s / Ebar_f)^(2/3),   Ebar = E / (1 - nu^2),

the flat state bifurcates into sinusoidal wrinkles of wavelength

    lambda = 2 pi h (Ebar_f / (3 Ebar_s))^(1/3)

(:func:`models.embedding.clusters.wrinkle_wavelength`; exact for an incompressible, infinitely
deep bonded substrate; -0.3 % on lambda at nu_s = 0.45 for a compressible one). A flat
compressed state is a stationary point, so the
film's geometry carries a small stress-free imperfection (its nodes above the interface raised)
and the compression is applied in ``steps`` increments up to ``strain_factor * eps_c``. The
imperfection is by default a narrow bump at the edge ``x = 0`` (flat spectrum over the roller
modes, see :class:`BilayerOptions`). With roller edges the admissible wrinkles are ``cos(n pi x
/ L)``, wavelengths ``2 L / n``: the measurement cannot be finer than that spacing, ``lambda^2
/ (2 L)`` near lambda (:func:`mode_spacing`).

Mesh: a structured triangle mesh (``dolfinx.mesh.create_rectangle``) whose rows are mapped to
``film_layers`` uniform rows in the film and ``substrate_layers`` rows in the substrate,
graded towards the interface (row ``j`` at depth ``H (1 - j/n)^grading``); columns give
``elements_per_wavelength`` elements per theoretical wavelength. Default P2.

The wavelength is :func:`validation.measure.dominant_wavelength` of the top nodes' vertical
displacement (:attr:`BilayerResult.top_w`) against their reference x (a material wavelength).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from meshes.errors import InputError, SolverError
from models.backend import MPI, dolfinx, ufl
from models.embedding.clusters import effective_modulus, wrinkle_wavelength
from models.materials import Material
from solvers.body_newton import EnergyNewton, NewtonOptions


@dataclass(frozen=True)
class BilayerOptions:
    """A plane-strain film/substrate bilayer and its loading.

    Attributes:
        film_E: film Young's modulus E_f [Pa].
        film_nu: film Poisson ratio [-].
        thickness: film thickness h [m].
        substrate_E: substrate Young's modulus E_s [Pa].
        substrate_nu: substrate Poisson ratio [-].
        periods: domain length L in theoretical wavelengths [-].
        depth: substrate depth H in theoretical wavelengths [-] (the wrinkle's decay length
            is lambda / (2 pi)).
        elements_per_wavelength: mesh columns per theoretical wavelength [-].
        film_layers: element rows through the film [-].
        substrate_layers: element rows through the substrate [-].
        grading: exponent of the substrate rows' grading towards the interface (1 = uniform).
        degree: Lagrange degree of the displacement (1 or 2).
        strain_factor: final compression as a multiple of eps_c [-], > 1.
        steps: load steps to the final compression [-].
        imperfection: amplitude of the film's initial vertical offset, in film thicknesses [-].
        imperfection_kind: ``"edge"``: a Gaussian bump of width ``lambda / 20`` at ``x = 0``
            (its projections on the roller modes ``cos(n pi x / L)`` are all alike near the
            critical one, so it favours no wavelength); ``"noise"``: uniform random offsets
            of the film's nodes (``seed``).
        seed: seed of the ``"noise"`` imperfection's random numbers.
        newton: the Newton solver's options.
        max_halvings: how often a failed load step is halved before ``SolverError``.

    """

    film_E: float = 5.0e7
    film_nu: float = 0.3
    thickness: float = 5.0e-4
    substrate_E: float = 5.0e4
    substrate_nu: float = 0.45
    periods: float = 8.0
    depth: float = 1.5
    elements_per_wavelength: int = 16
    film_layers: int = 2
    substrate_layers: int = 24
    grading: float = 2.0
    degree: int = 2
    strain_factor: float = 2.0
    steps: int = 10
    imperfection: float = 1.0e-2
    imperfection_kind: str = "edge"
    seed: int = 0
    newton: NewtonOptions = field(default_factory=lambda: NewtonOptions(rtol=1e-9, atol=1e-12,
                                                                        max_it=60))
    max_halvings: int = 6

    def __post_init__(self) -> None:
        for name in ("film_E", "thickness", "substrate_E", "periods", "depth", "grading"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise InputError(f"bilayer.{name}: must be > 0, got {value}")
        for name in ("film_nu", "substrate_nu"):
            if not -1.0 < getattr(self, name) < 0.5:
                raise InputError(f"bilayer.{name}: must be in (-1, 0.5), got "
                                 f"{getattr(self, name)}")
        for name in ("elements_per_wavelength", "film_layers", "substrate_layers", "steps"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"bilayer.{name}: must be >= 1, got {getattr(self, name)}")
        if self.degree not in (1, 2):
            raise InputError(f"bilayer.degree: must be 1 or 2, got {self.degree}")
        if not self.strain_factor > 1.0:
            raise InputError(f"bilayer.strain_factor: must be > 1, got {self.strain_factor}")
        if not self.imperfection >= 0.0:
            raise InputError(f"bilayer.imperfection: must be >= 0, got {self.imperfection}")
        if self.imperfection_kind not in ("edge", "noise"):
            raise InputError(f"bilayer.imperfection_kind: expected 'edge' or 'noise', got "
                             f"{self.imperfection_kind!r}")

    @property
    def film(self) -> Material:
        """The film's material."""
        return Material(E=self.film_E, nu=self.film_nu)

    @property
    def substrate(self) -> Material:
        """The substrate's material."""
        return Material(E=self.substrate_E, nu=self.substrate_nu)

    @property
    def wavelength(self) -> float:
        """Theoretical wavelength ``2 pi h (Ebar_f / (3 Ebar_s))^(1/3)`` [m]."""
        return wrinkle_wavelength(self.thickness, self.film_E, self.film_nu, self.substrate_E,
                                  self.substrate_nu)

    @property
    def critical_strain(self) -> float:
        """``eps_c = 1/4 (3 Ebar_s / Ebar_f)^(2/3)`` [-]."""
        ratio = 3.0 * effective_modulus(self.substrate_E, self.substrate_nu) / effective_modulus(
            self.film_E, self.film_nu)
        return 0.25 * ratio ** (2.0 / 3.0)

    @property
    def length(self) -> float:
        """Domain length L [m]."""
        return self.periods * self.wavelength

    @property
    def substrate_depth(self) -> float:
        """Substrate depth H [m]."""
        return self.depth * self.wavelength


@dataclass(frozen=True)
class BilayerResult:
    """What a bilayer run measured.

    Attributes:
        theory: theoretical wavelength [m].
        strain: final compressive strain [-].
        critical_strain: eps_c of the theory [-].
        dofs: displacement unknowns.
        newton_iterations: Newton iterations over all load steps.
        min_det_f: minimum det F at the end [-].
        wall_time: wall time of the solve [s].
        top_x: reference x of the top nodes [m] (sorted).
        top_w: vertical displacement of the top nodes [m] (same order).

    """

    theory: float
    strain: float
    critical_strain: float
    dofs: int
    newton_iterations: int
    min_det_f: float
    wall_time: float
    top_x: np.ndarray
    top_w: np.ndarray


def mode_spacing(options: BilayerOptions) -> float:
    """Relative spacing ``lambda / (2 L)`` of the admissible wavelengths ``2 L / n`` [-]."""
    return options.wavelength / (2.0 * options.length)


def row_heights(options: BilayerOptions) -> np.ndarray:
    """Heights of the mesh rows: graded substrate rows, then uniform film rows [m]."""
    ns, nf, depth = options.substrate_layers, options.film_layers, options.substrate_depth
    j = np.arange(ns + 1)
    substrate = depth * (1.0 - (1.0 - j / ns) ** options.grading)
    film = depth + options.thickness * np.arange(1, nf + 1) / nf
    return np.concatenate([substrate, film])


def bilayer_mesh(options: BilayerOptions, comm: MPI.Comm) -> dolfinx.mesh.Mesh:
    """Structured triangle mesh of the bilayer with rows at :func:`row_heights`."""
    rows = row_heights(options)
    n_rows = rows.size - 1
    nx = max(int(round(options.periods * options.elements_per_wavelength)), 1)
    mesh = dolfinx.mesh.create_rectangle(comm, [np.zeros(2), np.array([options.length, 1.0])],
                                         [nx, n_rows], dolfinx.mesh.CellType.triangle)
    x = mesh.geometry.x
    x[:, 1] = np.interp(x[:, 1], np.linspace(0.0, 1.0, n_rows + 1), rows)
    return mesh


def film_indicator(mesh: dolfinx.mesh.Mesh, interface: float) -> dolfinx.fem.Function:
    """DG0 indicator of the film: 1 on cells whose midpoint lies above ``interface``."""
    Q = dolfinx.fem.functionspace(mesh, ("DG", 0))
    chi = dolfinx.fem.Function(Q, name="film")
    chi.interpolate(lambda x: (x[1] > interface).astype(np.float64))
    return chi


def plane_strain_gradient(u: Any) -> Any:
    """``F = [[I + grad u, 0], [0, 1]]``: the 3-D deformation gradient of plane strain."""
    F2 = ufl.Identity(2) + ufl.grad(u)
    return ufl.as_matrix([[F2[0, 0], F2[0, 1], 0.0], [F2[1, 0], F2[1, 1], 0.0],
                          [0.0, 0.0, 1.0]])


def energy_form(options: BilayerOptions, u: Any, chi: Any) -> Any:
    """``Pi(u) = int chi psi_f(F) + (1 - chi) psi_s(F) dX`` (plane strain, per unit depth)."""
    F = plane_strain_gradient(u)
    dx = ufl.dx(metadata={"quadrature_degree": 2 * options.degree})
    return (chi * options.film.psi(F) + (1.0 - chi) * options.substrate.psi(F)) * dx


@dataclass
class _Loading:
    """The Dirichlet conditions and the moving edge's prescribed value."""

    bcs: list[Any]
    end: Any


def boundary_conditions(V: Any, length: float) -> _Loading:
    """Rollers: ``u_x = 0`` at x = 0, ``u_x = end`` at x = L, ``u_y = 0`` at y = 0."""
    mesh = V.mesh
    fdim = mesh.topology.dim - 1

    def component_bc(k: int, marker: Any, value: Any) -> Any:
        facets = dolfinx.mesh.locate_entities_boundary(mesh, fdim, marker)
        dofs = dolfinx.fem.locate_dofs_topological(V.sub(k), fdim, facets)
        return dolfinx.fem.dirichletbc(value, dofs, V.sub(k))

    end = dolfinx.fem.Constant(mesh, 0.0)
    tol = 1e-9 * length
    bcs = [component_bc(0, lambda x: np.abs(x[0]) < tol, dolfinx.fem.Constant(mesh, 0.0)),
           component_bc(0, lambda x: np.abs(x[0] - length) < tol, end),
           component_bc(1, lambda x: np.abs(x[1]) < tol, dolfinx.fem.Constant(mesh, 0.0))]
    return _Loading(bcs, end)


def imperfection_values(x: np.ndarray, options: BilayerOptions) -> np.ndarray:
    """Vertical offsets at reference abscissae ``x`` (``BilayerOptions.imperfection_kind``)."""
    amplitude = options.imperfection * options.thickness
    if options.imperfection_kind == "noise":
        return amplitude * np.random.default_rng(options.seed).uniform(-1.0, 1.0, x.shape)
    width = options.wavelength / 20.0
    return amplitude * np.exp(-0.5 * (x / width) ** 2)


def add_imperfection(mesh: dolfinx.mesh.Mesh, options: BilayerOptions) -> None:
    """Raise the film's mesh nodes above the interface by :func:`imperfection_values`.

    A geometric (stress-free) imperfection: the film is locally thicker by up to
    ``imperfection * h``; the interface and the substrate keep their shape.
    """
    x = mesh.geometry.x
    film = x[:, 1] > options.substrate_depth * (1.0 + 1e-12)
    x[film, 1] += imperfection_values(x[film, 0], options)


def apply_bcs(u: Any, loading: _Loading, value: float) -> None:
    """Set the moving edge's value and write every Dirichlet value into ``u``."""
    loading.end.value = value
    for bc in loading.bcs:
        bc.set(u.x.array)
    u.x.scatter_forward()


class Bilayer:
    """The bilayer problem: mesh, space, energy, Newton solver and load stepping.

    Args:
        options: geometry, materials, mesh and loading.
        comm: communicator of the mesh.

    """

    def __init__(self, options: BilayerOptions, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
        self.options = options
        self.mesh = bilayer_mesh(options, comm)
        add_imperfection(self.mesh, options)
        self.V = dolfinx.fem.functionspace(self.mesh, ("Lagrange", options.degree, (2,)))
        self.u = dolfinx.fem.Function(self.V, name="displacement")
        chi = film_indicator(self.mesh, options.substrate_depth)
        self.loading = boundary_conditions(self.V, options.length)
        film = options.film
        scale = (film.mu + film.lmbda) * options.length * options.thickness
        self.solver = EnergyNewton(energy_form(options, self.u, chi), self.u, self.loading.bcs,
                                   ufl.det(plane_strain_gradient(self.u)), 2 * options.degree,
                                   options.newton, energy_scale=scale)
        self.strain = 0.0
        self.iterations = 0

    def solve_to(self, strain: float) -> None:
        """Compress to ``strain`` from the current state, halving failed increments.

        Raises:
            SolverError: an increment failed ``max_halvings + 1`` times (state restored).

        """
        start, target_strain = self.u.x.array.copy(), strain
        increment, halvings = strain - self.strain, 0
        while self.strain < target_strain - 1e-14:
            saved = self.u.x.array.copy()
            trial = min(self.strain + increment, target_strain)
            apply_bcs(self.u, self.loading, -trial * self.options.length)
            result = self.solver.solve()
            self.iterations += result.iterations
            if result.converged:
                self.strain = trial
                continue
            self.u.x.array[:] = saved
            increment, halvings = 0.5 * increment, halvings + 1
            if halvings > self.options.max_halvings:
                self.u.x.array[:] = start
                raise SolverError(f"bilayer: load step to strain {trial:.4g} failed after "
                                  f"{halvings - 1} halvings ({result.describe()})")

    def top_profile(self) -> tuple[np.ndarray, np.ndarray]:
        """Return reference x and vertical displacement of the top dofs (gathered, sorted)."""
        coords = self.V.tabulate_dof_coordinates()
        n_owned = self.V.dofmap.index_map.size_local
        o = self.options
        top_y = o.substrate_depth + o.thickness
        tol = 0.25 * o.thickness / o.film_layers + o.imperfection * o.thickness
        top = np.flatnonzero(np.abs(coords[:n_owned, 1] - top_y) < tol)
        w = self.u.x.array.reshape(-1, 2)[top, 1]
        parts = self.mesh.comm.allgather((coords[top, 0], w))
        x_all = np.concatenate([p[0] for p in parts])
        w_all = np.concatenate([p[1] for p in parts])
        order = np.argsort(x_all)
        return x_all[order], w_all[order]


def run_bilayer(options: BilayerOptions, comm: MPI.Comm = MPI.COMM_WORLD) -> BilayerResult:
    """Build, perturb, compress in ``steps`` load steps; return the top surface's profile.

    Its wavelength is measured by :func:`validation.measure.dominant_wavelength` (the model
    layer does not import the application layer).
    """
    t0 = time.perf_counter()
    bilayer = Bilayer(options, comm)
    final = options.strain_factor * options.critical_strain
    for k in range(1, options.steps + 1):
        bilayer.solve_to(final * k / options.steps)
    x, w = bilayer.top_profile()
    dofs = bilayer.V.dofmap.index_map.size_global * bilayer.V.dofmap.index_map_bs
    return BilayerResult(theory=options.wavelength, strain=bilayer.strain,
                         critical_strain=options.critical_strain, dofs=int(dofs),
                         newton_iterations=bilayer.iterations,
                         min_det_f=bilayer.solver.min_det_f(),
                         wall_time=time.perf_counter() - t0, top_x=x, top_w=w)


__all__ = ["Bilayer", "BilayerOptions", "BilayerResult", "add_imperfection", "bilayer_mesh",
           "mode_spacing",
           "row_heights",
           "run_bilayer"]
