"""Two-way coupling (solvers/coupling.py): the cluster penalty as a quadratic term of the body.

The bar of tests/test_wrinkles/test_shell_stage.py compressed by 4 % in one frame with the demo's
1000x skin (E_f = 50 MPa on a 50 kPa body): body Newton with ``k_P ||H (x - B (X + u))||^2``
at fixed x, alternating with the shell solve, Anderson on the body load, converges.
Checks: the hook's Taylor test (energy, gradient, Hessian of the quadratic term in the body's
Newton), convergence, and the total force conservation ``sum_j F_j = sum_i f_i`` to 1e-10.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from support import LENGTH, SKIN, bar_scene

from meshes.errors import InputError
from models.backend import MPI
from models.coupling import penalty_force, penalty_term
from solvers.coupling import Anderson, CouplingOptions
from wrinkles.runner import Run, prepare, run_frames
from wrinkles.scene import scene_from_dict

MAX_IT = 60


def coupled_scene(max_iterations: int = MAX_IT) -> dict:
    shell = {"subdivision": {"levels": 1}, "skin": SKIN, "energy": {"k_P": 1.0e3},
             "solver": {"rtol": 1e-8, "max_iterations": 300}, "imperfection": 1e-3,
             "coupling": {"mode": "two_way"}}
    shell["solver"]["options"] = {"coupling.max_iterations": max_iterations,
                                  "coupling.scheme": "implicit"}
    return bar_scene((-0.04 * LENGTH, 0.0, 0.0), 1, shell)


def run_coupled(tmp: Path, **kwargs: int) -> Run:
    scene = scene_from_dict(coupled_scene(**kwargs), Path.cwd())
    return run_frames(prepare(scene, tmp, MPI.COMM_WORLD), lambda line: None)


@pytest.fixture(scope="module")
def implicit(tmp_path_factory) -> Run:
    return run_coupled(tmp_path_factory.mktemp("implicit"))


def test_quadratic_term_taylor(implicit):
    """E(u + e du) of the term: value, gradient and Hessian agree with finite differences
    (remainder slopes 2 and 3 for first- and second-order Taylor)."""
    shell, body = implicit.shell, implicit.body
    assert shell is not None
    rng = np.random.default_rng(1)
    term = penalty_term(shell.embedding, shell.clusters.H, shell.params.k_P,
                        shell.x - shell.rest + 1e-3 * rng.standard_normal(shell.x.shape),
                        body.V)
    u = term.c.duplicate()
    u.array[:] = 1e-2 * rng.standard_normal(u.array.size)
    du = term.c.duplicate()
    du.array[:] = 1e-2 * rng.standard_normal(du.array.size)
    g = term.gradient(u)
    Kdu = term.K.createVecLeft()
    term.K.mult(du, Kdu)
    e0, slope, curv = term.value(u), g.dot(du), Kdu.dot(du)
    eps = np.array([1e-1, 5e-2, 2.5e-2, 1.25e-2])
    r1, r2 = [], []
    for h in eps:
        w = u.copy()
        w.axpy(h, du)
        e = term.value(w)
        r1.append(abs(e - e0 - h * slope))
        r2.append(abs(e - e0 - h * slope - 0.5 * h * h * curv))
    p1 = np.polyfit(np.log(eps), np.log(r1), 1)[0]
    print("Taylor remainders", r1, r2, "slope", p1)
    assert p1 == pytest.approx(2.0, abs=0.05)
    # exact quadratic: the second-order remainder is round-off
    assert max(r2) <= 1e-10 * abs(e0)
    # the penalty value: E(u_body) = k_P ||H (x - y)||^2 at the run's state
    term = penalty_term(shell.embedding, shell.clusters.H, shell.params.k_P,
                        shell.x - shell.rest, body.V)
    hd = shell.clusters.H @ (shell.x - shell.y)
    assert term.value(body.u.x.petsc_vec) == pytest.approx(
        shell.params.k_P * float(np.sum(hd * hd)), rel=1e-9)


def test_implicit_converges(implicit):
    """The implicit scheme reaches the coupling fixed point with a converged shell; force
    conservation is checked with a real net force in the next test (at the converged state
    the net penalty force is ~0, so a sum check there would prove nothing)."""
    rec = implicit.records[-1].details
    shell = implicit.shell
    assert shell is not None
    print("implicit: coupling iterations", rec["coupling_iterations"], "change",
          rec["coupling_change"], "newton", rec.get("newton_iterations"))
    assert rec["coupling_change"] <= 1e-6
    assert rec["coupling_iterations"] < MAX_IT
    assert rec["shell_converged"]


def test_term_force_equals_penalty_force_sum(implicit):
    """For a shell displaced with a net force (random d plus a shift), the body force of the
    term, ``-sum_j (K u - c)_j``, equals ``sum_i f_i`` of the penalty force to 1e-10."""
    shell, body = implicit.shell, implicit.body
    assert shell is not None
    rng = np.random.default_rng(2)
    d = shell.x - shell.rest + 1e-3 * rng.standard_normal(shell.x.shape) + [2e-3, -1e-3, 5e-4]
    term = penalty_term(shell.embedding, shell.clusters.H, shell.params.k_P, d, body.V)
    g = term.gradient(body.u.x.petsc_vec)
    body_force = -MPI.COMM_WORLD.allreduce(g.array.reshape(-1, 3).sum(axis=0), op=MPI.SUM)
    f = penalty_force(shell.clusters.H, shell.params.k_P, shell.rest + d, shell.y)
    print("term force", body_force, "sum f", f.sum(axis=0), "scale", np.abs(f).sum())
    assert np.abs(f.sum(axis=0)).max() > 1e-3 * np.abs(f).sum()  # a real net force
    assert np.abs(body_force - f.sum(axis=0)).max() <= 1e-10 * np.abs(f).sum()


def test_anderson_solves_a_linear_fixed_point_in_n_plus_one_steps():
    """On a linear map ``x -> A x + b`` (n = 5, slowest contraction 0.99) Anderson with
    memory >= n is GMRES in disguise: exact after n + 1 images (error <= 1e-10), where the
    plain iteration still has 85 % of its initial error."""
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.standard_normal((5, 5)))
    a = q @ np.diag([0.99, 0.95, 0.9, 0.5, 0.1]) @ q.T
    b = rng.standard_normal((5, 1))
    x_star = np.linalg.solve(np.eye(5) - a, b)
    x, plain, acc = np.zeros((5, 1)), np.zeros((5, 1)), Anderson(memory=8)
    for _ in range(6):
        x = acc.relax(x, a @ x + b)
        plain = a @ plain + b
    err = float(np.linalg.norm(x - x_star) / np.linalg.norm(x_star))
    err_plain = float(np.linalg.norm(plain - x_star) / np.linalg.norm(x_star))
    print("Anderson error", err, "plain", err_plain)
    assert err <= 1e-10
    assert err_plain > 0.5


@pytest.mark.parametrize(("field", "value"), [("mode", "sideways"), ("memory", 0),
                                             ("max_iterations", 0), ("rtol", 0.0),
                                             ("scheme", "explicit")])
def test_coupling_options_reject_bad_values(field, value):
    """Bad coupling options raise InputError naming the field (the explicit scheme was
    removed: the monolithic solve was faster on every skin it was measured on)."""
    with pytest.raises(InputError, match=f"shell.coupling.{field}"):
        CouplingOptions(**{field: value})
