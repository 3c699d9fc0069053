"""Block-preconditioned CG for the joint body-shell Newton system (solvers/joint_krylov.py).

The bar of tests/support.py with the 1000x skin, two-way coupled, shell subdivided once. The
joint system of a coupled evaluation solved by CG against scipy's sparse direct solve of the
same matrix; its refusals of indefinite systems; and the product path (the shell's method
"multigrid" makes the coupled Newton use this CG) against the direct joint factorisation on
the stretched bar, whose minimum is unique.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from support import LENGTH, SKIN, bar_scene, dumps

from models.backend import MPI
from solvers.joint_krylov import BodyBlock, JointKrylovSystem
from solvers.monolithic import CoupledEnergy
from solvers.multigrid import MultigridLinearSystem, MultigridOptions
from wrinkles.runner import Run, prepare, run_frames
from wrinkles.scene import scene_from_dict
from wrinkles.two_way import CoupledStep


def two_way_bar(method: str, strain: float) -> dict:
    """The bar two-way coupled, stretched (> 0) or compressed (< 0) by ``strain`` in one frame."""
    shell = {"subdivision": {"levels": 1}, "skin": SKIN, "energy": {"k_P": 1.0e3},
             "solver": {"rtol": 1e-10, "max_iterations": 300, "method": method},
             "imperfection": 1e-3 if strain < 0 else 0.0, "coupling": {"mode": "two_way"}}
    return bar_scene((strain * LENGTH, 0.0, 0.0), 1, shell)


def run(tmp: Path, method: str, strain: float) -> Run:
    scene = scene_from_dict(two_way_bar(method, strain), Path.cwd())
    return run_frames(prepare(scene, tmp, MPI.COMM_WORLD), lambda line: None)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[tuple[str, float], Run]:
    return {(method, strain): run(tmp_path_factory.mktemp(method), method, strain)
            for method in ("direct", "multigrid") for strain in (0.04, -0.04)}


def coupled(r: Run) -> tuple[CoupledEnergy, CoupledStep]:
    step = r.body._solve
    assert isinstance(step, CoupledStep)
    energy, _ = next(iter(step.solvers.values()))
    return energy, step


def joint_system(r: Run, rtol: float) -> tuple[JointKrylovSystem, CoupledEnergy, np.ndarray]:
    """A fresh joint CG (fixed CG tolerance ``rtol``) and the converged state z."""
    energy, _ = coupled(r)
    assert r.shell is not None and r.shell.hierarchy is not None
    options = MultigridOptions(rtol=rtol, forcing="fixed", max_iterations=500)
    mg = MultigridLinearSystem(r.shell.hierarchy.prolongations(), options)
    system = JointKrylovSystem(mg, energy.shell.penalty_factor, energy.body_factor)
    z = np.vstack([r.shell.x, energy.body.get().reshape(-1, 3)]).reshape(-1)
    return system, energy, z


def joint_matrix(ev, tau: float) -> sp.csc_matrix:
    return (ev.hess + ev.penalty_factor.T @ ev.penalty_factor
            + tau * sp.identity(ev.hess.shape[0])).tocsc()


@pytest.mark.parametrize("strain", [0.04, -0.04])
def test_cg_solves_the_joint_system(runs, strain):
    """At the converged state (SPD joint Hessian) CG reaches the direct solution: relative
    error <= 1e-8 for rtol 1e-10 (the shell block by one V-cycle per iteration, the body block
    exactly); measured 55 and 68 CG iterations (stretched / compressed), errors 1e-11 and 2e-11."""
    system, energy, z = joint_system(runs[("direct", strain)], 1e-10)
    ev = energy.evaluate(z, order=2)
    report = system.factorize(ev, 0.0)
    assert report.usable_spd
    b = -ev.grad + 1e-3 * np.linalg.norm(ev.grad) * np.random.default_rng(3).standard_normal(
        ev.grad.size)
    x = system.solve(b)
    exact = spla.spsolve(joint_matrix(ev, 0.0), b)
    error = np.linalg.norm(x - exact) / np.linalg.norm(exact)
    print("CG iterations", system.stats.iterations, "relative error", error)
    assert error <= 1e-8
    assert system.stats.iterations[-1] <= 80
    assert system.stats.true_residuals[-1] <= 1e-9


def test_indefinite_joint_system_is_refused(runs):
    """A shift below minus the smallest eigenvalue makes M indefinite: the set-up or the CG
    says so (no direction is returned), as the shell Newton's shift ladder expects."""
    system, energy, z = joint_system(runs[("direct", -0.04)], 1e-8)
    ev = energy.evaluate(z, order=2)
    lam_min = spla.eigsh(joint_matrix(ev, 0.0), k=1, sigma=0.0, which="LM")[0][0]
    report = system.factorize(ev, -2.0 * abs(lam_min) - 1e-3)
    refused = not report.usable_spd or not np.all(np.isfinite(system.solve(-ev.grad)))
    assert refused


def test_body_block_not_spd_fails_the_set_up(runs):
    """A body block that is not positive definite fails the set-up with a named reason."""
    system, energy, z = joint_system(runs[("direct", 0.04)], 1e-8)
    ev = energy.evaluate(z, order=2)
    k_x, k_u = ev.blocks
    bad = dataclasses.replace(ev, blocks=(k_x, -sp.identity(k_u.shape[0], format="csr")))
    report = system.factorize(bad, 0.0)
    assert not report.usable_spd and "body block" in report.reason


def laplacian_3d(n: int) -> sp.csr_matrix:
    """The SPD 1D Laplacian of ``n`` nodes (Dirichlet ends) times I_3: spectrum in (0, 12)."""
    lap = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    return sp.kron(lap, sp.identity(3)).tocsr()


@pytest.mark.parametrize("rows", [6, 90])
def test_body_block_keeps_its_factor_while_close(rows):
    """The body block's factor is kept for a shift within ``shift_tolerance`` x its mean
    diagonal (1.7 - 3.3 here: 0.5 apart is kept, 1.0 apart refactorises), up to ``max_age``
    reuses, and never after :meth:`invalidate` or a failed (indefinite) factorisation; a kept
    factor solves with the factorised matrix, a new one with the new matrix. A penalty factor
    with fewer rows than the body's 60 dofs is factorised in the augmented form, one with
    more assembled; both solve ``M_uu`` to 1e-10."""
    k_u = laplacian_3d(20)
    factor = sp.random(rows, k_u.shape[0], density=0.3 * 6 / rows, random_state=1,
                       format="csr")
    block = BodyBlock(factor, max_age=2, shift_tolerance=0.3)
    assert block.augmented is (rows < k_u.shape[0])
    m = (k_u + factor.T @ factor).tocsc()
    eye = sp.identity(k_u.shape[0], format="csc")
    b = np.random.default_rng(0).standard_normal(k_u.shape[0])
    assert block.factorize(k_u, 0.0).usable_spd
    scale = float(np.mean(m.diagonal()))
    assert 1.7 < scale < 3.3  # 0.3 x scale in (0.5, 1.0)
    assert block.factorize(k_u, 0.5).reason == "reused"  # 0.5 <= 0.3 x scale
    np.testing.assert_allclose(block.solve(b), spla.spsolve(m, b), rtol=1e-10)
    assert block.factorize(k_u, 1.0).reason != "reused"  # 1.0 > 0.3 x scale: refactorised
    np.testing.assert_allclose(block.solve(b), spla.spsolve(m + eye, b), rtol=1e-10)
    assert [block.factorize(k_u, 1.0).reason for _ in range(3)] == ["reused", "reused", "ok"]
    block.invalidate()
    assert block.factorize(k_u, 1.0).reason != "reused"
    assert (block.factorizations, block.reuses) == (4, 3)
    assert not block.factorize(-k_u, 0.0).usable_spd  # indefinite: never kept
    assert block.factorize(-k_u, 0.0).reason != "reused"
    assert block.factorizations == 6


def test_cg_with_a_kept_body_factor_solves_the_new_system(runs):
    """A set-up whose shift moved within the tolerance keeps the body block's factor; the CG
    still solves the new joint matrix (the preconditioner is stale, the product exact): the
    direct solution of ``M + tau I`` to 1e-8 for rtol 1e-10."""
    system, energy, z = joint_system(runs[("direct", -0.04)], 1e-10)
    ev = energy.evaluate(z, order=2)
    assert system.factorize(ev, 0.0).usable_spd
    tau = 0.1 * float(np.mean(np.abs(ev.blocks[1].diagonal())))
    assert system.factorize(ev, tau).usable_spd
    assert (system.body.factorizations, system.body.reuses) == (1, 1)
    b = -ev.grad
    x = system.solve(b)
    exact = spla.spsolve(joint_matrix(ev, tau), b)
    error = np.linalg.norm(x - exact) / np.linalg.norm(exact)
    print("CG iterations", system.stats.iterations, "relative error", error)
    assert error <= 1e-8


def test_both_body_block_forms_solve_the_joint_system(runs):
    """The joint CG with the body block augmented (forced: the bar's 516 body dofs have more
    penalty rows) reaches the direct solution as the assembled one does: relative error
    <= 1e-8 for rtol 1e-10, within 2 CG iterations of it (measured 73 and 73, 6.9e-11)."""
    system, energy, z = joint_system(runs[("direct", -0.04)], 1e-10)
    ev = energy.evaluate(z, order=2)
    b = -ev.grad
    exact = spla.spsolve(joint_matrix(ev, 0.0), b)
    iterations = []
    for augmented in (False, True):
        system.body = BodyBlock(energy.body_factor, augmented=augmented)
        assert system.body.augmented is augmented
        assert system.factorize(ev, 0.0).usable_spd
        x = system.solve(b)
        iterations.append(system.stats.iterations[-1])
        error = np.linalg.norm(x - exact) / np.linalg.norm(exact)
        print("augmented", augmented, "CG iterations", iterations[-1], "relative error", error)
        assert error <= 1e-8
    assert abs(iterations[0] - iterations[1]) <= 2


def test_product_path_uses_the_joint_cg(runs):
    """With the shell's method "multigrid" the coupled Newton solves by the joint CG (CG
    iterations counted, no factorisation of the joint matrix), whose shell block is the
    shell solver's own multigrid (not run by the monolithic step); "direct" factorises."""
    for method, strain in runs:
        r = runs[(method, strain)]
        _, step = coupled(r)
        report = step.reports[-1]
        assert report.converged
        assert (report.krylov_iterations > 0) is (method == "multigrid")
        if method == "multigrid":
            ((_, solver),) = step.solvers.values()
            assert isinstance(solver.krylov, JointKrylovSystem)
            assert r.shell is not None and solver.krylov.shell is r.shell.solver.krylov


def test_cg_path_equals_the_direct_path_stretched(runs):
    """Stretched bar (one minimum): the coupled solve by CG lands on the direct solve's
    state, u and x to 1e-6 relative (measured 1.6e-10 and 1.6e-11)."""
    states = {}
    for method in ("direct", "multigrid"):
        r = runs[(method, 0.04)]
        energy, _ = coupled(r)
        states[method] = (energy.body.get(), r.shell.x.reshape(-1))
    for k, name in enumerate(("u", "x")):
        a, b = states["direct"][k], states["multigrid"][k]
        rel = np.linalg.norm(a - b) / np.linalg.norm(a)
        print(name, "relative difference", rel)
        assert rel <= 1e-6


def test_cg_path_compressed_reaches_a_coupled_minimiser(runs):
    """Compressed bar (wrinkles, many minima): the CG path converges to a state whose coupled
    gradient is below the tolerance, with an energy within 1 % of the direct path's (measured
    0.05070 against 0.05081)."""
    energies = {}
    for method in ("direct", "multigrid"):
        r = runs[(method, -0.04)]
        energy, step = coupled(r)
        report = step.reports[-1]
        assert report.converged and report.grad_norm <= report.tolerance
        energies[method] = report.energy
    print(energies)
    assert energies["multigrid"] == pytest.approx(energies["direct"], rel=1e-2)


@pytest.mark.mpi
def test_cg_path_on_two_ranks_equals_serial(runs, mpiexec, tmp_path):
    """`mpiexec -n 2 wrinkles run` of the compressed bar on the CG path: every rank solves
    the joint system (the body's gradient and Hessian gathered), so the frame equals the serial
    one: the same coupled Newton iterations, energies to 1e-9 relative."""
    scene = tmp_path / "bar.toml"
    scene.write_text(dumps(two_way_bar("multigrid", -0.04)))
    out = tmp_path / "out"
    proc = mpiexec(["-m", "wrinkles", "run", str(scene), "--out", str(out)], n=2, timeout=300)
    assert proc.returncode == 0, proc.stderr
    frame = json.loads((out / "summary.json").read_text())["frames"][0]
    _, step = coupled(runs[("multigrid", -0.04)])
    serial = step.reports[-1]
    print(frame["details"]["coupling_iterations"], serial.iterations,
          frame["details"]["shell_energy"])
    assert frame["details"]["coupling_iterations"] == serial.iterations
    assert frame["details"]["coupling_converged"]
    serial_shell = runs[("multigrid", -0.04)].records[-1].details["shell_energy"]
    assert frame["details"]["shell_energy"] == pytest.approx(serial_shell, rel=1e-9)
