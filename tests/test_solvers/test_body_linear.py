"""The body's Newton systems by CG + GAMG: the same steps as the LU, the LU where CG fails."""

from __future__ import annotations

import numpy as np
import pytest

import solvers.body_linear as body_linear
from meshes.errors import InputError
from models.backend import MPI, PETSc, dolfinx
from models.body import BodyOptions
from models.contact import ContactOptions
from models.materials import Material
from solvers.body import Body
from solvers.body_linear import IterativeBodySolve, choose_body_method
from solvers.body_newton import NewtonOptions

MAT = Material(model="neo_hookean", E=1.0e4, nu=0.3, density=100.0)


def dropped_block(method: str) -> Body:
    """A soft 0.3 m block falling 5 mm onto a floor (stiff contact in the later steps)."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0.005], [0.3, 0.3, 0.305]],
                                   [4, 4, 4], dolfinx.mesh.CellType.tetrahedron)
    floor = ContactOptions(obstacle="plane", point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0))
    options = BodyOptions(dynamics="implicit_euler", dt=0.01, gravity=(0.0, 0.0, -9.81),
                          contacts=(floor,))
    return Body(mesh, MAT, options, NewtonOptions(method=method))


def steps(body: Body, n: int) -> tuple[list[int], np.ndarray]:
    """Newton iterations of ``n`` steps and the final displacement."""
    its = [body.step().newton_iterations for _ in range(n)]
    return its, body.u.x.array.copy()


def test_the_choice_is_by_the_factorisation_cost_at_both_sides_of_the_crossover():
    threshold = body_linear.ITERATIVE_FLOPS
    assert choose_body_method(0.5 * threshold) == "direct"
    assert choose_body_method(threshold) == "direct"
    assert choose_body_method(1.01 * threshold) == "iterative"
    assert choose_body_method(8.8e9) == "iterative"  # the cinolib ball's 13 515 dofs
    assert choose_body_method(1.44e9) == "iterative"  # the bunny's 14 010 dofs
    assert choose_body_method(3.3e8) == "direct"  # ball_sofa.toml's sofa, 4 386 dofs
    assert choose_body_method(5.4e8) == "direct"  # the demo's sofa in P2, 6 087 dofs


def test_iterative_steps_are_the_direct_ones():
    """Free fall, then contact with the floor: the same Newton iterations and states."""
    direct_its, direct_u = steps(dropped_block("direct"), 12)
    body = dropped_block("iterative")
    its, u = steps(body, 12)
    facts = body.linear_facts()
    print("direct", direct_its, "iterative", its, facts,
          "max |du|", float(np.abs(u - direct_u).max()))
    assert body.contacts and body.energies()["contact"] > 0.0  # it did land
    assert its == direct_its
    assert np.abs(u - direct_u).max() <= 1e-9 * np.abs(direct_u).max()
    assert facts["method"] == "iterative" and facts["cg_solves"] == sum(its)
    assert facts["lu_fallbacks"] == 0 and facts["cg_iterations"] >= facts["cg_solves"]


def test_a_failed_cg_solve_is_made_by_the_lu(monkeypatch):
    """CG capped at one iteration fails every solve: the LU makes them, the same steps."""
    direct_its, direct_u = steps(dropped_block("direct"), 4)
    monkeypatch.setattr(body_linear, "MAX_CG_ITERATIONS", 1)
    body = dropped_block("iterative")
    its, u = steps(body, 4)
    facts = body.linear_facts()
    assert its == direct_its
    assert np.abs(u - direct_u).max() <= 1e-9 * np.abs(direct_u).max()
    assert facts["lu_fallbacks"] == facts["cg_solves"] == sum(its)


def test_negative_curvature_is_solved_by_the_lu():
    """A shifted 1-D Laplacian with negative eigenvalues: CG fails, the LU solves it."""
    n = 60
    dense = 2.0 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1) - 0.5 * np.eye(n)
    assert np.linalg.eigvalsh(dense).min() < 0.0
    A = PETSc.Mat().createAIJ((n, n), nnz=3, comm=PETSc.COMM_SELF)
    for i, j in zip(*np.nonzero(dense), strict=True):
        A.setValue(int(i), int(j), dense[i, j])
    A.assemble()
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    ksp.setOperators(A)
    ksp.setType("preonly")
    context = IterativeBodySolve("test_body_linear_")
    ksp.getPC().setType(PETSc.PC.Type.PYTHON)
    ksp.getPC().setPythonContext(context)
    b, x = A.createVecs()
    b.setArray(np.arange(1.0, n + 1.0))
    ksp.solve(b, x)
    assert context.solves == 1 and context.fallbacks == 1
    assert np.allclose(x.getArray(), np.linalg.solve(dense, np.arange(1.0, n + 1.0)),
                       rtol=1e-10)
    context.destroy()


@pytest.mark.parametrize(("threshold", "method"), [(0.0, "iterative"), (1e30, "direct")])
def test_auto_switches_after_the_first_factorisation_by_its_cost(monkeypatch, threshold,
                                                                 method):
    """``auto``: the first step factorises; the later ones use what its cost chose."""
    monkeypatch.setattr(body_linear, "ITERATIVE_FLOPS", threshold)
    direct_its, direct_u = steps(dropped_block("direct"), 3)
    body = dropped_block("auto")
    its, u = steps(body, 3)
    facts = body.linear_facts()
    assert facts["method"] == method
    assert its == direct_its
    assert np.abs(u - direct_u).max() <= 1e-9 * np.abs(direct_u).max()
    if method == "iterative":
        assert facts["cg_solves"] == sum(its) - its[0]


@pytest.mark.parametrize(("options", "names"), [
    ({"method": "cg"}, "newton.method"),
    ({"method": "iterative", "petsc": {"ksp_type": "gmres"}}, "leave newton.petsc"),
    ({"method": "iterative", "linear_solver": "superlu_dist"}, "newton.linear_solver"),
])
def test_bad_method_refused(options, names):
    with pytest.raises(InputError, match=names):
        NewtonOptions(**options)
