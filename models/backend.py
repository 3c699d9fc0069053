"""The one adapter between this code and the dolfinx 0.11 / PETSc / MPI stack.

Every other module imports ``MPI``, ``PETSc``, ``dolfinx``, ``ufl`` and ``basix`` from here,
never directly: the ``dolfinx-solver-real`` wheel requires ``import dolfinx_solver`` before
mpi4py, petsc4py or dolfinx are loaded (it orders one MPI runtime ahead of the compiled
bindings), and keeping the dolfinx-version-specific calls in this module means a dolfinx
upgrade touches one file.

The stack is loaded on first use (lazy loading as in the Scientific Python ecosystem's SPEC 1):
the five names are stand-ins that import the whole stack, in the wheel's order, when one of
their attributes is first read (:func:`load_stack`). Importing this code therefore neither
loads dolfinx nor initialises MPI: a command that reads a scene and sizes its mesh (the rank
count of a serial ``wrinkles run``, ``wrinkles plot``) does without the stack.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Mapping
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import basix
    import basix.ufl
    import dolfinx
    import dolfinx.fem
    import dolfinx.fem.petsc
    import dolfinx.io
    import dolfinx.mesh
    import numpy.typing as npt
    import ufl
    from mpi4py import MPI
    from petsc4py import PETSc

STACK: tuple[str, ...] = ("basix", "basix.ufl", "dolfinx", "dolfinx.fem", "dolfinx.fem.petsc",
                          "dolfinx.io", "dolfinx.mesh", "ufl", "mpi4py.MPI", "petsc4py.PETSc")
"""The modules of the stack, imported in this order after ``dolfinx_solver``."""


@functools.cache
def load_stack() -> None:
    """Import the stack (``dolfinx_solver`` first), start PETSc's log; once per process.

    Importing ``mpi4py.MPI`` initialises MPI. PETSc's list of unread options at exit is
    switched off: it would also name options of a solver a run never calls (the static Newton
    of a dynamic body); the scene's expert options are checked where they are set
    (``solvers.body_newton.unread_options``: an InputError naming the key).
    """
    import dolfinx_solver  # noqa: F401  (must precede mpi4py, petsc4py and dolfinx)

    for name in STACK:
        importlib.import_module(name)
    begin_petsc_log()
    from petsc4py import PETSc

    PETSc.Options().setValue("options_left", "0")


class _OnFirstUse:
    """Stand-in for a module of the stack: the first attribute read loads the stack.

    Each attribute read is kept on the stand-in, so later reads cost a plain attribute
    lookup (the modules' classes, functions and constants do not change once imported).
    """

    def __init__(self, name: str) -> None:
        self.__dict__["_name"] = name
        self.__dict__["_module"] = None

    def __getattr__(self, attr: str) -> Any:
        module: ModuleType | None = self._module
        if module is None:
            load_stack()
            module = self.__dict__["_module"] = importlib.import_module(self._name)
        value = self.__dict__[attr] = getattr(module, attr)
        return value

    def __repr__(self) -> str:
        return f"<module {self._name!r}, loaded on first use>"


if not TYPE_CHECKING:
    MPI = _OnFirstUse("mpi4py.MPI")
    PETSc = _OnFirstUse("petsc4py.PETSc")
    basix = _OnFirstUse("basix")
    dolfinx = _OnFirstUse("dolfinx")
    ufl = _OnFirstUse("ufl")

__all__ = ["MPI", "PETSc", "basix", "dolfinx", "ufl", "begin_petsc_log", "load_stack",
           "mesh_from_arrays",
           "vector_space", "is_affine", "global_scalar", "quadrature_expression",
           "global_min_on_cells", "exterior_facet_domain", "with_facet_domains",
           "assemble_snes_residual", "petsc_error_message", "set_from_options"]


def begin_petsc_log() -> None:
    """Start PETSc's default performance log (its event timers) on every rank.

    ``PETSc.Log.begin()`` (``PetscLogDefaultBegin``) is collective on ``PETSC_COMM_WORLD``:
    called from code that runs on rank 0 only (a serial shell solve) it deadlocks. It is
    therefore called once when the stack loads, which every rank does (every module reaches
    the stack through this one), and :mod:`solvers.linear` only reads the events. Idempotent.
    """
    from petsc4py import PETSc

    if not PETSc.Log.isActive():
        PETSc.Log.begin()


def set_from_options(solver: Any, options: Mapping[str, Any]) -> None:
    """Set ``options`` under ``solver``'s prefix and call its ``setFromOptions``.

    dolfinx's ``petsc_options`` do the same but leave the prefix pushed on PETSc's options
    database when PETSc refuses an option (every later option then lands under it) and delete
    the options before a factor reads its own (``mat_*``) at its first set-up. Here the prefix
    is popped in every case and the options stay (under the solver's own prefix).

    Raises:
        PETSc.Error: PETSc refused an option (:func:`petsc_error_message` gives its words).

    """
    table = PETSc.Options()
    table.prefixPush(solver.getOptionsPrefix())
    try:
        for key, value in options.items():
            table.setValue(key, value)
        solver.setFromOptions()
    finally:
        table.prefixPop()


def petsc_error_message(err: Exception) -> str:
    """PETSc's own words in a petsc4py ``PETSc.Error``: its message lines, not the call stack.

    ``str(err)`` is ``"error code N"`` followed by ``"[rank] Function() at file:line"`` frames
    and ``"[rank] message"`` lines; the message lines are joined with ``"; "`` (the first line
    when there are none).
    """
    lines = str(err).splitlines()
    words = [line.split("] ", 1)[1] for line in lines[1:]
             if line.startswith("[") and "] " in line and "() at " not in line]
    return "; ".join(words) if words else (lines[0] if lines else repr(err))


# --- body helpers (dolfinx-0.11-specific calls used by models/body.py) ------------------------

def mesh_from_arrays(comm: MPI.Comm, points: object, tets: object) -> dolfinx.mesh.Mesh:
    """Build a distributed P1 tetrahedral mesh; rank 0 holds the arrays, others pass empty ones.

    Args:
        comm: Communicator of the mesh.
        points: ``(n, 3)`` float64 vertex coordinates (``(0, 3)`` on ranks other than 0).
        tets: ``(m, 4)`` int64 vertex indices of the tetrahedra (``(0, 4)`` off rank 0).

    Returns:
        The mesh, partitioned over ``comm`` by dolfinx's default graph partitioner.

    """
    import numpy as np

    x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cells = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    domain = ufl.Mesh(basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,)))
    return dolfinx.mesh.create_mesh(comm, cells, domain, x)


def vector_space(mesh: dolfinx.mesh.Mesh, degree: int) -> dolfinx.fem.FunctionSpace:
    """Vector Lagrange space of ``degree`` with one 3-vector per node (block size 3)."""
    return dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (mesh.geometry.dim,)))


def is_affine(mesh: dolfinx.mesh.Mesh) -> bool:
    """Whether the mesh's cells are straight (a degree-1 coordinate element).

    On straight cells ``grad u`` of a P1 field is constant on each cell.
    """
    return all(cmap.degree == 1 for cmap in mesh.geometry.cmaps)


def global_scalar(form: dolfinx.fem.Form) -> float:
    """Assemble a compiled scalar form and sum it over the ranks of its mesh."""
    local = dolfinx.fem.assemble_scalar(form)
    return float(form.mesh.comm.allreduce(local, op=MPI.SUM))


def quadrature_expression(expr: ufl.core.expr.Expr, mesh: dolfinx.mesh.Mesh,
                          degree: int) -> dolfinx.fem.Expression:
    """Compile a UFL expression for evaluation at the degree-``degree`` quadrature points."""
    import numpy as np

    points, _ = basix.make_quadrature(mesh.basix_cell(), degree)
    return dolfinx.fem.Expression(expr, np.asarray(points))


def global_min_on_cells(expression: dolfinx.fem.Expression, mesh: dolfinx.mesh.Mesh) -> float:
    """Minimum of a compiled expression over all points of all owned cells, over all ranks.

    NaN values (e.g. ``det F`` of a NaN field) count as ``-inf`` so that they are never
    mistaken for a valid state.
    """
    import numpy as np

    n_local = mesh.topology.index_map(mesh.topology.dim).size_local
    values = expression.eval(mesh, np.arange(n_local, dtype=np.int32))
    local = float(np.min(values)) if values.size else float("inf")
    if not np.all(np.isfinite(values)):
        local = float("-inf")
    return float(mesh.comm.allreduce(local, op=MPI.MIN))


def exterior_facet_domain(mesh: dolfinx.mesh.Mesh, facets: object) -> npt.NDArray[Any]:
    """Return the integration entities of exterior facets: ``(cell, local facet)`` pairs, flattened.

    Args:
        mesh: The mesh (its facet-cell connectivity is created here).
        facets: Indices of exterior facets owned by this rank.

    Returns:
        An int32 array ``[c_0, f_0, c_1, f_1, ...]``, the form of a ``ds`` subdomain's entities
        (``ufl.Measure("ds", subdomain_data=[(id, entities)])``, :func:`with_facet_domains`).

    """
    import numpy as np

    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    mesh.topology.create_connectivity(tdim, tdim - 1)
    return np.asarray(dolfinx.fem.compute_integration_domains(
        dolfinx.fem.IntegralType.exterior_facet, mesh.topology,
        np.asarray(facets, dtype=np.int32)), dtype=np.int32)


def with_facet_domains(form: dolfinx.fem.Form,
                       domains: Mapping[int, object]) -> dolfinx.fem.Form:
    """Return the compiled ``form`` with the entities of its exterior-facet subdomains replaced.

    The generated kernels, coefficients and constants are shared with ``form`` (no UFL
    processing, no JIT): only the lists of ``(cell, local facet)`` pairs of the subdomain ids
    in ``domains`` change (:func:`exterior_facet_domain`); the other integrals keep theirs.
    The form's exterior-facet integrals must all carry an id present in ``domains``.

    Raises:
        ValueError: ``form`` has an exterior-facet integral whose id is not in ``domains``.

    """
    cpp = form._cpp_object
    facet = dolfinx.fem.IntegralType.exterior_facet
    subdomains: dict[object, list[tuple[int, object]]] = {}
    for kind in cpp.integral_types:
        ids = sorted({int(i) for i in _integral_ids(form, kind)})
        if kind == facet:
            missing = [i for i in ids if i not in domains]
            if missing:
                raise ValueError(f"with_facet_domains: no entities for ds({missing[0]})")
            subdomains[kind] = [(i, domains[i]) for i in ids]
        else:
            subdomains[kind] = [(i, cpp.domains(kind, i)) for i in ids if i >= 0]
    module: Any = form.module  # one compiled form: one CFFI module
    ptr = module.ffi.cast("uintptr_t", module.ffi.addressof(form.ufcx_form))
    rebuilt = dolfinx.fem.forms.form_cpp_class(form.dtype)(
        [ptr], cpp.function_spaces, cpp.coefficients, cpp.constants, subdomains, [], cpp.mesh)
    return dolfinx.fem.Form(rebuilt, form.ufcx_form, form.code, form.module)


def assemble_snes_residual(x: Any, b: Any, u: dolfinx.fem.Function,
                           residual: dolfinx.fem.Form, jacobian: dolfinx.fem.Form,
                           bcs: list[dolfinx.fem.DirichletBC], work: Any) -> None:
    """Assemble the SNES residual of ``residual`` at ``x`` into ``b``, as dolfinx does (collective).

    dolfinx's ``assemble_residual`` assembles ``F(x)``, lifts the Dirichlet values, ``b -= J
    (g - x)`` on the rows coupled to Dirichlet dofs, and sets ``b = x - g`` on the Dirichlet
    rows. Where ``x`` already equals ``g`` on every Dirichlet dof (``max |x - g| = 0``, tested
    in ``work``, a vector of ``b``'s layout) the lifting adds exactly zero and is left out:
    the same vector, without packing the Jacobian form's coefficients and assembling its
    cells at the boundary. A Newton iteration from a start that meets its Dirichlet values
    stays there (identity rows, zero residual rows). Otherwise dolfinx's assembly runs.
    """
    fem: Any = dolfinx.fem.petsc  # singledispatch functions: (Vec, Form) overloads
    insert, add = PETSc.InsertMode.INSERT, PETSc.InsertMode.ADD
    x.ghostUpdate(addv=insert, mode=PETSc.ScatterMode.FORWARD)
    work.zeroEntries()
    fem.set_bc(work, bcs, x0=x, alpha=-1.0)
    if work.norm(PETSc.NormType.NORM_INFINITY) != 0.0:
        fem.assemble_residual(None, x, b, u, residual, jacobian, bcs)
        return
    fem.assign(x, u)
    with b.localForm() as local:
        local.set(0.0)
    fem.assemble_vector(b, residual)
    b.ghostUpdate(addv=add, mode=PETSc.ScatterMode.REVERSE)
    fem.set_bc(b, bcs, x0=x, alpha=-1.0)
    b.ghostUpdate(addv=insert, mode=PETSc.ScatterMode.FORWARD)


def _integral_ids(form: dolfinx.fem.Form, kind: object) -> list[int]:
    """Return the subdomain ids of the integrals of type ``kind`` in the compiled form."""
    ufcx = form.ufcx_form
    offsets = ufcx.form_integral_offsets
    kind_index = int(kind.value)  # type: ignore[attr-defined]
    return [int(ufcx.form_integral_ids[j]) for j in range(offsets[kind_index],
                                                         offsets[kind_index + 1])]
