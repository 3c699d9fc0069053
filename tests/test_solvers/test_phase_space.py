"""Wrinkle-phase coarse space: gradients, hats, the Galerkin projection, fewer CG iterations."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp
import shellcases

from meshes.errors import InputError
from meshes.shells import grid_plate, icosphere
from models.backend import PETSc
from solvers.multigrid import MultigridLinearSystem, MultigridOptions, ShellHierarchy
from solvers.phase_space import (
    PhaseSpace,
    UnionSum,
    hat_frames,
    hat_matrix,
    surface_gradients,
)
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver

FAST = MultigridOptions(rtol=1e-8, fallback=False, eigen_estimate="solve", level_format="sbaij")
"""benchmarks/iterative.py's fast multigrid, CG to the true residual 1e-8."""


def test_surface_gradient_of_a_linear_field_is_its_tangential_part() -> None:
    pts, faces = grid_plate(4, 3, 1.0, 0.7)
    q, _ = np.linalg.qr(np.random.default_rng(0).standard_normal((3, 3)))
    tilted = pts @ q.T  # the plate rotated: its normal is q e_z
    a = np.array([0.3, -1.2, 0.8])
    grads = surface_gradients(tilted, faces)
    normal = q[:, 2]
    tangential = a - (a @ normal) * normal
    got = np.column_stack([g @ (tilted @ a) for g in grads])  # (n, 3): D_k of f = a . X
    print(f"max |D f - P_T a| = {np.max(np.abs(got - tangential)):.1e}")
    assert np.max(np.abs(got - tangential)) < 1e-12
    sphere, sfaces = icosphere(2)  # curved: D of a constant is zero, D x is a projector
    dx = np.stack([np.column_stack([g @ sphere[:, c] for g in surface_gradients(sphere, sfaces)])
                   for c in range(3)])
    assert np.max(np.abs(sum(g @ np.ones(len(sphere)) for g in
                             surface_gradients(sphere, sfaces)))) < 1e-12
    trace = np.einsum("cvc->v", dx)  # tr(D x) = 2 on a surface (the tangent projector)
    assert np.allclose(trace, 2.0, atol=0.05)


def test_hats_are_a_partition_of_unity_and_levels_are_checked() -> None:
    hier = ShellHierarchy.build(*grid_plate(3, 3), levels=2)
    subs = hier.subdivision.matrices
    for level in (0, 1):
        hats = hat_matrix(subs, level)
        assert hats.shape == (len(hier.vertices), hier.level_sizes[level])
        assert np.allclose(np.asarray(hats.sum(axis=1)).ravel(), 1.0, atol=1e-14)
        frames = hat_frames(hier.vertices, hier.faces, hats)  # tangent, orthonormal
        assert np.allclose(frames[:, :, 2], 0.0, atol=1e-14)
        gram = np.einsum("jad,jbd->jab", frames, frames)
        assert np.allclose(gram, np.eye(2), atol=1e-14)
    with pytest.raises(InputError, match="phase_level"):
        hat_matrix(subs, 2)
    with pytest.raises(InputError, match="phase_level"):
        MultigridOptions(phase_level=-1)
    with pytest.raises(InputError, match="phase_space: needs the shell's rest geometry"):
        MultigridLinearSystem(hier.prolongations(), MultigridOptions(phase_space=True))


def test_correction_is_the_a_orthogonal_projection_after_new_fields() -> None:
    """``Q A Q = Q`` with Z's values changed twice (the reused MatPtAP sees new values)."""
    hier = ShellHierarchy.build(*grid_plate(4, 4), levels=2)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=8)
    ev = energy.evaluate(x0, hessian="gauss_newton")
    assert ev.hess is not None and ev.penalty_factor is not None
    mg = MultigridLinearSystem(hier.prolongations(), replace(FAST, phase_space=True),
                               geometry=(hier.vertices, hier.faces))
    rng = np.random.default_rng(2)
    phase = mg.phase
    assert isinstance(phase, PhaseSpace)
    for amplitude in (1e-2, 3e-2):
        x = x0 + amplitude * rng.standard_normal(x0.shape)
        mg.set_state(x, energy.target)
        mg.factorize(ev, 0.5)
        r = rng.standard_normal(mg.n)
        q_r, qaq_r = _vec(mg.n), _vec(mg.n)
        phase.correct(_vec(mg.n, r), q_r)
        phase.correct(_vec(mg.n, mg.apply(q_r.getArray())), qaq_r)
        gap = np.linalg.norm(qaq_r.getArray() - q_r.getArray()) / np.linalg.norm(q_r.getArray())
        print(f"amplitude {amplitude}: |QAQ r - Q r| / |Q r| = {gap:.1e}")
        assert gap < 1e-8
        mg.factorize(ev, 2.0)  # the same evaluation shifted: Z^T A Z + 1.5 Z^T Z
        assert phase._gram[1] is not None  # the shift-only path ran
        phase.correct(_vec(mg.n, r), q_r)
        phase.correct(_vec(mg.n, mg.apply(q_r.getArray())), qaq_r)
        gap = np.linalg.norm(qaq_r.getArray() - q_r.getArray()) / np.linalg.norm(q_r.getArray())
        print(f"  shifted without the fine product: |QAQ r - Q r| / |Q r| = {gap:.1e}")
        assert gap < 1e-8
    mg.set_state(x0, None)  # an energy without a penalty target: d = x - rest positions
    mg.factorize(ev, 0.5)
    z = phase._z_held()  # new fields: the shift enters as tau Z^T Z of the new Z
    assert phase._gram[1] is not None
    assert abs(phase._gram[1] - z.T @ z).max() < 1e-13 * abs(z.T @ z).max()
    phase.correct(_vec(mg.n, r), q_r)
    phase.correct(_vec(mg.n, mg.apply(q_r.getArray())), qaq_r)
    assert np.linalg.norm(qaq_r.getArray() - q_r.getArray()) < 1e-8 * np.linalg.norm(
        q_r.getArray())


def _vec(n: int, values: np.ndarray | None = None) -> PETSc.Vec:
    """A sequential PETSc vector (zeros or a copy of ``values``)."""
    v = PETSc.Vec().createSeq(n, comm=PETSc.COMM_SELF)
    v.setArray(np.zeros(n) if values is None else np.ascontiguousarray(values))
    return v


@pytest.fixture(scope="module")
def wrinkled() -> tuple[ShellHierarchy, object, np.ndarray]:
    """A 49 x 49 compressed plate at its wrinkled minimum (direct Newton, exact Hessian)."""
    hier = ShellHierarchy.build(*grid_plate(6, 6), levels=3)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=32)
    x, report = ShellNewtonSolver(energy, ShellNewtonOptions(
        rtol=1e-8, hessian="exact", far_hessian="gauss_newton")).minimize(x0)
    assert report.converged and np.max(np.abs(x[:, 2])) > 0.01  # it wrinkles
    return hier, energy, x


def cg_iterations(wrinkled, phase: bool) -> tuple[int, float]:
    """CG iterations and true residual of the exact-Hessian Newton system at the minimum."""
    hier, energy, x = wrinkled
    ev = energy.evaluate(x, hessian="exact")
    assert ev.grad is not None
    mg = MultigridLinearSystem(hier.prolongations(), MultigridOptions(
        rtol=1e-8, fallback=False, eigen_estimate="solve", level_format="sbaij",
        phase_space=phase), geometry=(hier.vertices, hier.faces))
    mg.set_state(x, energy.target)
    mg.factorize(ev, 0.0)
    rhs = np.random.default_rng(5).standard_normal(mg.n)  # every mode, the soft band too
    dx = mg.solve(rhs)
    return mg.stats.iterations[-1], mg.true_residual(dx, rhs)


def test_phase_space_cuts_cg_iterations_at_the_wrinkled_minimum(wrinkled) -> None:
    plain, plain_res = cg_iterations(wrinkled, phase=False)
    phase, phase_res = cg_iterations(wrinkled, phase=True)
    print(f"CG to 1e-8 at the wrinkled minimum: multigrid {plain} its (true residual "
          f"{plain_res:.1e}), + phase space {phase} its ({phase_res:.1e})")
    assert plain_res < 1e-7 and phase_res < 1e-7
    assert phase < 0.7 * plain


def test_newton_with_phase_space_reaches_the_direct_minimiser(wrinkled) -> None:
    """Same minimiser and Newton iterations as the multigrid alone, fewer CG iterations
    (measured 128 against 199 in 5 Newton iterations)."""
    hier, energy, x_min = wrinkled
    start = x_min.copy()
    start[:, 0] += 2e-3 * np.sin(7.0 * hier.vertices[:, 1])  # a perturbed warm start
    reports = {}
    for phase in (False, True):
        opts = ShellNewtonOptions(rtol=1e-8, hessian="exact", linear_method="multigrid",
                                  multigrid=MultigridOptions(rtol=1e-4, fallback=False,
                                                             eigen_estimate="solve",
                                                             phase_space=phase))
        solver = ShellNewtonSolver(energy, opts, hierarchy=hier)  # type: ignore[arg-type]
        x, report = solver.minimize(start)
        gap = float(np.max(np.abs(x - x_min)))
        print(f"phase space {phase}: {report.summary()}; max |x - x_direct| = {gap:.1e}")
        assert report.converged and gap < 1e-6
        reports[phase] = report
    assert reports[True].iterations == reports[False].iterations
    assert reports[True].krylov_iterations < 0.8 * reports[False].krylov_iterations


def flat_compressed_plate() -> tuple[Any, MultigridLinearSystem]:
    """The flat compressed plate's exact-Hessian evaluation (indefinite: it buckles) and a
    phase-space multigrid at its state."""
    hier = ShellHierarchy.build(*grid_plate(6, 6), levels=3)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=32)
    mg = MultigridLinearSystem(hier.prolongations(), replace(FAST, phase_space=True),
                               geometry=(hier.vertices, hier.faces))
    mg.set_state(x0, energy.target)
    return energy.evaluate(x0, hessian="exact"), mg


def test_indefinite_phase_matrix_leaves_the_correction_out() -> None:
    """At the flat compressed start the exact Hessian is indefinite and ``Z^T A Z`` shows it:
    that matrix's CG runs on the multigrid alone (and meets the negative curvature: no
    direction); shifted far enough, the correction is back and CG converges."""
    ev, mg = flat_compressed_plate()
    report = mg.factorize(ev, 0.0)
    assert report.usable_spd and mg.stats.indefinite_skips == 1
    assert not mg._phase_ready and mg._ksp is not None  # the multigrid alone
    assert not np.all(np.isfinite(mg.solve(-ev.grad)))
    scale = float(np.mean(np.abs(ev.hess.diagonal())))
    report = mg.factorize(ev, 10.0 * scale)  # shifted far enough: SPD, correction in use
    assert report.usable_spd and mg._phase_ready and mg.stats.indefinite_skips == 1
    dx = mg.solve(-ev.grad)
    assert mg.true_residual(dx, -ev.grad) < 1e-7


def test_union_sum_equals_the_scipy_sum_of_its_parts() -> None:
    """Weighted sums on the union pattern equal scipy's, values changing in fixed patterns."""
    rng = np.random.default_rng(4)
    a = sp.random(30, 30, density=0.15, random_state=rng, format="csr")
    b = sp.random(30, 30, density=0.1, random_state=rng, format="csr")
    union = UnionSum({"a": a, "b": b})
    assert union.pattern.has_sorted_indices
    rows = np.repeat(np.arange(30), np.diff(union.pattern.indptr))
    assert np.array_equal(rows[union.diagonal], np.arange(30))  # the full diagonal is in
    assert np.array_equal(union.pattern.indices[union.diagonal], np.arange(30))
    for _ in range(2):
        a.data, b.data = rng.standard_normal(a.nnz), rng.standard_normal(b.nnz)
        values = np.zeros(union.pattern.nnz)
        union.add(values, "a", a)
        union.add(values, "b", b, -2.5)
        expected = (a - 2.5 * b).toarray()
        assert np.abs(union.matrix(values).toarray() - expected).max() < 1e-15
        assert np.array_equal(values[union.diagonal], np.diag(expected))
    assert not union.has_penalty and UnionSum({"penalty": b}).has_penalty


def test_an_inactive_phase_space_solves_as_the_multigrid_alone_and_rejoins(wrinkled) -> None:
    """``use_phase_space(False)``: the set-up builds no ``A_Z`` and CG takes the multigrid's
    own iterations and solution (bitwise); active again, the space rebuilds its test fields
    and its CG equals a fresh phase-space system's."""
    hier, energy, x = wrinkled
    ev = energy.evaluate(x, hessian="exact")
    rhs = np.random.default_rng(5).standard_normal(3 * len(hier.vertices))

    def system(phase: bool) -> MultigridLinearSystem:
        mg = MultigridLinearSystem(hier.prolongations(), replace(FAST, phase_space=phase),
                                   geometry=(hier.vertices, hier.faces))
        mg.set_state(x, energy.target)
        return mg

    def solved(mg: MultigridLinearSystem) -> tuple[np.ndarray, int]:
        mg.factorize(ev, 0.0)
        return mg.solve(rhs), mg.stats.iterations[-1]

    toggled = system(True)
    toggled.use_phase_space(False)
    off, off_its = solved(toggled)
    assert not toggled._phase_ready and not toggled.phase_active  # SPD: CG never joins it
    plain, plain_its = solved(system(False))
    assert off_its == plain_its and np.array_equal(off, plain)
    toggled.use_phase_space(True)
    on, on_its = solved(toggled)
    fresh, fresh_its = solved(system(True))
    print(f"CG iterations: inactive {off_its}, multigrid alone {plain_its}, active again "
          f"{on_its}, fresh phase space {fresh_its}")
    assert toggled._phase_ready and on_its == fresh_its < plain_its
    assert np.allclose(on, fresh, rtol=0, atol=1e-12 * np.abs(fresh).max())


def test_negative_curvature_brings_an_inactive_phase_space_in() -> None:
    """The flat compressed plate buckles: with the space inactive, the unshifted CG meets
    negative curvature, the space joins, and the shifted set-up after it uses it."""
    ev, mg = flat_compressed_plate()
    mg.use_phase_space(False)
    mg.factorize(ev, 0.0)
    assert not mg._phase_ready and mg.stats.indefinite_skips == 0  # no A_Z built
    assert not np.all(np.isfinite(mg.solve(-ev.grad)))
    assert mg.negative_curvature and mg.phase_active
    scale = float(np.mean(np.abs(ev.hess.diagonal())))
    assert mg.factorize(ev, 10.0 * scale).usable_spd and mg._phase_ready
    dx = mg.solve(-ev.grad)
    assert mg.true_residual(dx, -ev.grad) < 1e-7
