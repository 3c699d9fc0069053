"""Sparse direct solvers on shell-like systems: accuracy, reuse, augmented penalty, inertia."""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from meshes.errors import InputError
from meshes.shells import grid_plate, icosphere, perturb
from models.shell.dofs import stencil_dofs
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.reorder import reorder_mesh
from models.shell.rest import RestState
from models.shell.topology import ShellTopology
from solvers.linear import (
    MUMPS_ORDERINGS,
    ORDERING_CANDIDATES,
    AugmentedPenaltySolver,
    DiagonalScale,
    LinearSolverOptions,
    ShiftOptions,
    SparseDirectSolver,
    cheapest_ordering,
    true_residual,
)
from solvers.shell_newton import ShellNewtonOptions, minimize

CASES = [
    ("mumps", "cholesky", "aij"),
    ("mumps", "cholesky", "sbaij"),
    ("mumps", "ldlt", "aij"),
    ("mumps", "ldlt", "sbaij"),
    ("mumps", "lu", "aij"),
    ("petsc", "cholesky", "aij"),
    ("superlu_dist", "lu", "aij"),
    ("scipy", "cholesky", "aij"),
    ("scipy", "lu", "aij"),
]
PETSC_REUSE = [c for c in CASES if c[0] in ("mumps", "petsc")]


def _hinge_stencils(nx: int, ny: int) -> tuple[np.ndarray, int]:
    points, faces = grid_plate(nx, ny)
    topo = ShellTopology.from_faces(faces, len(points))
    return topo.hinges, len(points)


def shell_like(nx: int, ny: int, rng: np.random.Generator, ridge: float = 1e-3) -> sp.csr_matrix:
    """SPD matrix with the bending pattern: sum of random rank-6 PSD 12x12 hinge blocks + ridge.

    Like a shell Hessian it is a sum of PSD stencil blocks, each with a null space (rigid
    modes), made definite by a small diagonal (a penalty-like term).
    """
    hinges, n = _hinge_stencils(nx, ny)
    dofs = stencil_dofs(hinges)
    b = rng.standard_normal((len(hinges), 12, 6))
    blocks = b @ b.transpose(0, 2, 1)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    a = sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
    a = a + ridge * sp.identity(3 * n, format="csr")
    a.sum_duplicates()
    a.sort_indices()
    return a


def same_pattern(a: sp.csr_matrix, data: np.ndarray) -> sp.csr_matrix:
    return sp.csr_matrix((data, a.indices, a.indptr), shape=a.shape)


def options(case: tuple[str, str, str]) -> LinearSolverOptions:
    return LinearSolverOptions(backend=case[0], symmetric=case[1], matrix_format=case[2])


@pytest.mark.parametrize("case", CASES, ids=["-".join(c) for c in CASES])
def test_solve_and_refactorise(case: tuple[str, str, str], rng: np.random.Generator) -> None:
    a = shell_like(12, 10, rng)
    b = rng.standard_normal(a.shape[0])
    solver = SparseDirectSolver(a, options(case))
    first = solver.factorize(a)
    x = solver.solve(b)
    res1 = true_residual(a, x, b)
    # new values, same pattern: D A D with a random positive diagonal D (still SPD)
    d = 1.0 + rng.random(a.shape[0])
    rows = np.repeat(np.arange(a.shape[0]), np.diff(a.indptr))
    a2 = same_pattern(a, a.data * d[rows] * d[a.indices])
    second = solver.factorize(a2)
    x2 = solver.solve(b)
    res2 = true_residual(a2, x2, b)
    ref = sla.spsolve(a2.tocsc(), b)
    print(f"{case}: residual first {res1:.2e} refactorised {res2:.2e} "
          f"|x2-ref|/|ref| {np.linalg.norm(x2 - ref) / np.linalg.norm(ref):.2e}")
    assert first.success and second.success
    assert res1 < 1e-10 and res2 < 1e-10
    assert np.linalg.norm(x2 - ref) < 1e-8 * np.linalg.norm(ref)
    assert np.linalg.norm(x2 - x) > 1e-3 * np.linalg.norm(x)  # the new values were used


@pytest.mark.parametrize("case", PETSC_REUSE, ids=["-".join(c) for c in PETSC_REUSE])
def test_second_factorisation_reuses_analysis(case: tuple[str, str, str],
                                              rng: np.random.Generator) -> None:
    a = shell_like(30, 30, rng)
    solver = SparseDirectSolver(a, options(case))
    reports = [solver.factorize(same_pattern(a, a.data * s)) for s in (1.0, 2.0, 3.0)]
    for r in reports:
        print(f"{case}: analysis {r.analysis_time:.4f} s numeric {r.numeric_time:.4f} s "
              f"reused {r.reused_analysis}")
    assert not reports[0].reused_analysis and reports[0].analysis_time > 0
    assert all(r.reused_analysis and r.analysis_time == 0 for r in reports[1:])
    b = rng.standard_normal(a.shape[0])
    assert true_residual(same_pattern(a, a.data * 3.0), solver.solve(b), b) < 1e-10


def penalty_factor(n_vertices: int, clusters: int, rng: np.random.Generator) -> sp.csr_matrix:
    """G = sqrt(2 k_P) (H kron I_3) with H rows of normalised random weights over vertex sets."""
    rows, cols, vals = [], [], []
    for c in range(clusters):
        members = rng.choice(n_vertices, size=12, replace=False)
        w = rng.random(12)
        rows.append(np.full(12, c))
        cols.append(members)
        vals.append(w / w.sum())
    h = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(clusters, n_vertices))
    return (np.sqrt(2.0 * 1e3) * sp.kron(h, sp.identity(3))).tocsr()


@pytest.mark.parametrize("backend,symmetric", [("mumps", "ldlt"), ("mumps", "lu"),
                                               ("superlu_dist", "lu"), ("scipy", "lu")])
def test_augmented_equals_assembled(backend: str, symmetric: str,
                                    rng: np.random.Generator) -> None:
    a = shell_like(12, 10, rng, ridge=0.0)  # singular alone: only A + G^T G is definite
    n_vertices = a.shape[0] // 3
    g = penalty_factor(n_vertices, 40, rng)
    rhs = rng.standard_normal(a.shape[0])
    aug = AugmentedPenaltySolver(a, g, LinearSolverOptions(backend=backend, symmetric=symmetric))
    report = aug.factorize(a, g)
    dx = aug.solve(rhs)
    full = (a + g.T @ g).tocsc()
    ref = sla.spsolve(full, rhs)
    rel = np.linalg.norm(dx - ref) / np.linalg.norm(ref)
    res = true_residual(full, dx, rhs)
    print(f"augmented {backend}/{symmetric}: |dx-ref|/|ref| {rel:.2e} residual {res:.2e} "
          f"negative pivots {report.negative_pivots} (m = {g.shape[0]})")
    assert report.success
    assert rel < 1e-10 and res < 1e-10
    if backend == "mumps" and symmetric == "ldlt":
        assert report.negative_pivots == g.shape[0] and report.indefinite is False
    # refactorisation with new values of both blocks and the same patterns
    g2 = sp.csr_matrix((g.data * 2.0, g.indices, g.indptr), shape=g.shape)
    aug.factorize(a, g2)
    ref2 = sla.spsolve((a + g2.T @ g2).tocsc(), rhs)
    assert np.linalg.norm(aug.solve(rhs) - ref2) < 1e-10 * np.linalg.norm(ref2)


INDEFINITE = [("mumps", "cholesky", "aij"), ("mumps", "cholesky", "sbaij"),
              ("mumps", "ldlt", "aij"), ("petsc", "cholesky", "aij"),
              ("scipy", "cholesky", "aij")]


@pytest.mark.parametrize("case", INDEFINITE, ids=["-".join(c) for c in INDEFINITE])
def test_indefinite_detected_and_shifted(case: tuple[str, str, str],
                                         rng: np.random.Generator) -> None:
    a = shell_like(6, 5, rng)
    eig = np.linalg.eigvalsh(a.toarray())
    sigma = 0.5 * (eig[6] + eig[7])  # exactly 7 eigenvalues below sigma
    indefinite = (a - sigma * sp.identity(a.shape[0])).tocsr()
    indefinite.sort_indices()
    solver = SparseDirectSolver(indefinite, options(case))
    shift = ShiftOptions(initial=1e-6, growth=10.0, max_shifts=12)
    reports = solver.factorize_shifted(indefinite, shift)
    lam_min = eig[0] - sigma
    print(f"{case}: lambda_min {lam_min:.3e}; attempts " + ", ".join(
        f"(tau {r.shift:.1e}, neg {r.negative_pivots}, ok {r.success})" for r in reports))
    assert reports[0].negative_pivots == 7 and reports[0].indefinite
    # every attempt's pivot count is the inertia of the shifted matrix (Sylvester)
    for r in reports:
        assert r.negative_pivots == int(np.count_nonzero(eig - sigma + r.shift < 0))
    last = reports[-1]
    assert last.usable_spd and last.negative_pivots == 0 and last.shift > 0
    assert lam_min + last.shift > 0 > lam_min + last.shift / shift.growth
    b = rng.standard_normal(a.shape[0])
    shifted = indefinite + last.shift * sp.identity(a.shape[0])
    assert true_residual(shifted, solver.solve(b), b) < 1e-10


def test_pattern_and_option_errors(rng: np.random.Generator) -> None:
    a = shell_like(4, 4, rng)
    solver = SparseDirectSolver(a, LinearSolverOptions(backend="scipy"))
    other = (a + sp.random(*a.shape, density=0.01, random_state=1)).tocsr()
    with pytest.raises(InputError, match="pattern"):
        solver.factorize(other)
    with pytest.raises(InputError, match="LinearSolverOptions.backend"):
        LinearSolverOptions(backend="cholmod")
    with pytest.raises(InputError, match="LinearSolverOptions.symmetric"):
        LinearSolverOptions(backend="superlu_dist", symmetric="cholesky")
    with pytest.raises(InputError, match="LinearSolverOptions.ordering"):
        LinearSolverOptions(backend="mumps", ordering="rcm")
    with pytest.raises(InputError, match="LinearSolverOptions.matrix_format"):
        LinearSolverOptions(backend="petsc", matrix_format="sbaij")
    with pytest.raises(InputError, match="ShiftOptions.growth"):
        ShiftOptions(growth=1.0)
    with pytest.raises(InputError, match="LinearSolverOptions.mumps_refinement"):
        LinearSolverOptions(mumps_refinement=-1)
    with pytest.raises(InputError, match="symmetric"):
        AugmentedPenaltySolver(a, penalty_factor(a.shape[0] // 3, 3, rng),
                               LinearSolverOptions(symmetric="cholesky"))


RANK_LOCAL_SCRIPT = """
import numpy as np, scipy.sparse as sp
from models.backend import MPI
from solvers.linear import LinearSolverOptions, SparseDirectSolver, true_residual
rank = MPI.COMM_WORLD.rank
rng = np.random.default_rng(rank)
n = 300 + 30 * rank                      # a different system on each rank
q = sp.random(n, n, density=0.02, random_state=rank)
a = (q @ q.T + sp.identity(n)).tocsr()
a.sort_indices()
b = rng.standard_normal(n)
for backend in ("mumps", "petsc", "superlu_dist"):
    opts = LinearSolverOptions(backend=backend, symmetric="lu" if backend == "superlu_dist"
                               else "cholesky")
    solver = SparseDirectSolver(a, opts)
    report = solver.factorize(a)
    res = true_residual(a, solver.solve(b), b)
    print(f"rank {rank} {backend} ok={report.success} residual={res:.1e}")
"""


@pytest.mark.mpi
def test_rank_local_solves_under_mpi(mpiexec) -> None:
    """Two ranks each factorise their own system on PETSc.COMM_SELF (no collective hang)."""
    proc = mpiexec(["-c", RANK_LOCAL_SCRIPT], n=2, timeout=120)
    print(proc.stdout, proc.stderr[-2000:])
    assert proc.returncode == 0
    # the two ranks share stdout, so their lines may interleave: parse records, not lines
    records = re.findall(r"rank (\d) (\S+) ok=(\w+) residual=([-+0-9.e]+)", proc.stdout)
    assert len(records) == 6 and all(ok == "True" for _, _, ok, _ in records)
    assert all(float(res) < 1e-12 for *_, res in records)


SINGULAR = [("mumps", "cholesky", "aij"), ("mumps", "ldlt", "sbaij"), ("mumps", "lu", "aij"),
            ("petsc", "cholesky", "aij"), ("superlu_dist", "lu", "aij"),
            ("scipy", "cholesky", "aij")]


@pytest.mark.parametrize("case", SINGULAR, ids=["-".join(c) for c in SINGULAR])
def test_failed_factorisation_detected_and_recovered(case: tuple[str, str, str],
                                                     rng: np.random.Generator) -> None:
    a = shell_like(6, 5, rng)
    rows = np.repeat(np.arange(a.shape[0]), np.diff(a.indptr))
    dead = (rows // 3 == 7) | (a.indices // 3 == 7)  # vertex 7's rows and columns are zero
    singular = same_pattern(a, np.where(dead, 0.0, a.data))
    solver = SparseDirectSolver(a, options(case))
    failed = solver.factorize(singular)
    print(f"{case}: {failed.reason}")
    assert not failed.success and not failed.usable_spd
    shifted = solver.factorize_shifted(singular, ShiftOptions())
    assert shifted[0].success is False and shifted[-1].success and shifted[-1].shift > 0
    # after a failure the same solver factorises a regular matrix of the pattern again
    assert solver.factorize(a).success
    b = rng.standard_normal(a.shape[0])
    assert true_residual(a, solver.solve(b), b) < 1e-10


def shell_hessian(level: int = 3) -> tuple[sp.csr_matrix, np.ndarray]:
    """Gauss-Newton Hessian of a perturbed icosphere shell (membrane + bending + diagonal
    penalty, the ``local`` system of benchmarks/shell_solve.py) and its gradient."""
    points, faces = reorder_mesh(*icosphere(level))[:2]
    topo = ShellTopology.from_faces(faces, len(points))
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, hessian_mode="gauss_newton")
    energy = ShellEnergy(topo, RestState.from_positions(topo, points), params,
                         H=sp.identity(len(points), format="csr"))
    ev = energy.evaluate(perturb(points, 0.01, seed=4), order=2)
    assert ev.hess is not None and ev.grad is not None
    return ev.hess, ev.grad


ORDERING_CASES = [("mumps", o) for o in MUMPS_ORDERINGS] + [("petsc", "nd"), ("petsc", "rcm")]


@pytest.mark.parametrize("case", ORDERING_CASES, ids=["-".join(c) for c in ORDERING_CASES])
def test_every_ordering_solves_the_shell_hessian(case: tuple[str, str]) -> None:
    a, g = shell_hessian()
    solver = SparseDirectSolver(a, LinearSolverOptions(case[0], "cholesky", ordering=case[1]))
    report = solver.factorize(a)
    res = true_residual(a, solver.solve(-g), -g)
    print(f"{case}: factor entries {report.factor_nnz}, residual {res:.1e}")
    assert report.success and report.negative_pivots == 0
    assert res < 1e-10
    solver.destroy()


def test_metis_has_the_least_fill() -> None:
    """The default MUMPS ordering (METIS) gives fewer factor entries than AMD / AMF / PORD on a
    shell Hessian (the basis of the default, see LinearSolverOptions.ordering; INFOG(29) counts
    the full-rank entries, so BLR does not enter)."""
    a, _ = shell_hessian(4)
    fill: dict[str, int] = {}
    for ordering in ("metis", "amd", "amf", "pord"):
        solver = SparseDirectSolver(a, LinearSolverOptions(ordering=ordering))
        nnz = solver.factorize(a).factor_nnz
        assert nnz is not None
        fill[ordering] = nnz
        solver.destroy()
    print("factor entries per ordering:", fill)
    assert LinearSolverOptions().resolved_ordering == "metis"
    assert all(fill["metis"] < fill[o] for o in ("amd", "amf", "pord"))


def _squared_grid_blocks(cells: int) -> sp.csr_matrix:
    """``L^2 (x) B``: a grid Laplacian squared (two-ring stencil) over 3 x 3 SPD blocks, the
    pattern family of the phase space's ``A_Z`` (hats coupled to their hats' neighbours)."""
    t = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(cells, cells))
    lap = sp.kron(t, sp.identity(cells)) + sp.kron(sp.identity(cells), t) \
        + 1e-3 * sp.identity(cells * cells)
    return sp.csr_matrix(sp.kron(lap @ lap, np.ones((3, 3)) + 3.0 * np.eye(3)))


@pytest.mark.parametrize(("cells", "winner"), [(20, "amf"), (30, "metis")])
def test_the_cheapest_ordering_is_the_one_of_fewest_flops(cells: int, winner: str,
                                                          rng: np.random.Generator) -> None:
    """Neither candidate ordering wins on every pattern (measured analysis flops: 20 x 20
    cells AMF 1.31e7 against METIS 1.37e7; 30 x 30 METIS 5.46e7 against AMF 7.10e7):
    ``cheapest_ordering`` keeps the solver of the fewer flops, factorised, and it solves."""
    a = _squared_grid_blocks(cells)
    flops = {}
    for ordering in ORDERING_CANDIDATES:
        solver = SparseDirectSolver(a, LinearSolverOptions(symmetric="ldlt", ordering=ordering))
        flops[ordering] = solver.factorize(a).factor_flops
        solver.destroy()
    print(f"{cells} x {cells}: analysis flops {flops}")
    assert min(flops, key=lambda o: flops[o]) == winner
    chosen, report = cheapest_ordering(a, LinearSolverOptions(symmetric="ldlt"))
    assert chosen.options.ordering == winner and report.factor_flops == flops[winner]
    assert report.success and report.negative_pivots == 0
    b = rng.standard_normal(a.shape[0])
    assert true_residual(a, chosen.solve(b), b) < 1e-10
    named, _ = cheapest_ordering(a, LinearSolverOptions(symmetric="ldlt", ordering="amd"))
    assert named.options.ordering == "amd" and named.stats.factorizations == 1
    for solver in (chosen, named):
        solver.destroy()


@pytest.fixture(scope="module")
def sphere_10k() -> tuple[sp.csr_matrix, np.ndarray]:
    """The 10k-vertex shell Hessian: large enough fronts for BLR to compress."""
    return shell_hessian(5)


@pytest.mark.parametrize("tolerance, refinement, bound", [(1e-10, 0, 1e-10), (1e-6, 0, 1e-5),
                                                          (1e-6, 3, 1e-10)])
def test_blr_residual_and_refinement(tolerance: float, refinement: int, bound: float,
                                     sphere_10k: tuple[sp.csr_matrix, np.ndarray]) -> None:
    """BLR (ICNTL(35)) trades accuracy for speed; refinement (ICNTL(10)) buys it back."""
    a, g = sphere_10k
    opts = LinearSolverOptions(mumps_blr=True, mumps_blr_tolerance=tolerance,
                               mumps_refinement=refinement)
    if tolerance == 1e-10 and refinement == 0:
        assert opts == LinearSolverOptions()  # the default is this case
    blr = SparseDirectSolver(a, opts)
    report = blr.factorize(a)
    res_blr = true_residual(a, blr.solve(-g), -g)
    print(f"BLR {tolerance:g}, {refinement} refinement steps: residual {res_blr:.1e}; "
          f"MUMPS memory {report.memory_mb} MB")
    assert report.success and report.negative_pivots == 0
    assert res_blr < bound
    if refinement == 0:
        assert res_blr > 1e-14  # the factor is really compressed (exact: ~3e-16)
    blr.destroy()


@pytest.mark.slow
def test_newton_converges_with_blr(sphere_10k: tuple[sp.csr_matrix, np.ndarray]) -> None:
    """Shell Newton on the 10k sphere (pulled back to rest from a perturbed state) converges
    with a BLR factor at tolerance 1e-6 (inexact Newton) as with the exact factor."""
    points, faces = reorder_mesh(*icosphere(5))[:2]
    topo = ShellTopology.from_faces(faces, len(points))
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, hessian_mode="gauss_newton")
    energy = ShellEnergy(topo, RestState.from_positions(topo, points), params,
                         H=sp.identity(len(points), format="csr"))
    x0 = perturb(points, 0.01, seed=4)
    blr = LinearSolverOptions(mumps_blr=True, mumps_blr_tolerance=1e-6)
    exact = LinearSolverOptions(mumps_blr=False)
    x_exact, r_exact = minimize(energy, x0,  # type: ignore[arg-type]
                                ShellNewtonOptions(rtol=1e-10, linear=exact))
    x_blr, r_blr = minimize(energy, x0,  # type: ignore[arg-type]
                            ShellNewtonOptions(rtol=1e-10, linear=blr))
    print(f"Newton iterations exact {r_exact.iterations} {r_exact.grad_norms}, "
          f"BLR {r_blr.iterations} {r_blr.grad_norms}")
    assert r_exact.converged and r_blr.converged
    assert r_blr.iterations <= r_exact.iterations + 2
    assert np.max(np.abs(x_blr - x_exact)) < 1e-8


def test_aij_backend_shares_the_pattern_arrays() -> None:
    """No persistent copy of the constant pattern or the values in the solver (memory at 640k)."""
    a, _ = shell_hessian(2)
    solver = SparseDirectSolver(a)
    backend = solver._backend
    assert np.shares_memory(backend._indices, a.indices)  # type: ignore[attr-defined]
    assert not hasattr(solver, "_data")
    solver.factorize(a, shift=1.0)  # the shifted values are a temporary, a is untouched
    assert np.array_equal(a.data, shell_hessian(2)[0].data)
    solver.destroy()


def test_out_of_core_factor(sphere_10k: tuple[sp.csr_matrix, np.ndarray]) -> None:
    """ICNTL(22) = 1 keeps the factors on disk: same accuracy, less MUMPS memory."""
    a, g = sphere_10k
    memory: dict[bool, float] = {}
    for ooc in (False, True):
        solver = SparseDirectSolver(a, LinearSolverOptions(mumps_out_of_core=ooc,
                                                           mumps_blr=False))
        report = solver.factorize(a)
        res = true_residual(a, solver.solve(-g), -g)
        print(f"out of core {ooc}: MUMPS memory {report.memory_mb} MB, residual {res:.1e}")
        assert report.success and res < 1e-13 and report.memory_mb is not None
        memory[ooc] = report.memory_mb
        solver.destroy()
    assert memory[True] < 0.5 * memory[False]


def test_diagonal_scale_matches_scipy_and_follows_new_patterns() -> None:
    """Cached positions give ``mean |diag|`` of each matrix; a new pattern is searched again."""
    rng = np.random.default_rng(3)
    scale = DiagonalScale()
    first = sp.random(40, 40, density=0.2, random_state=rng, format="csr") + sp.eye(40) * -3.0
    first = sp.csr_matrix(first)
    first.sort_indices()
    assert scale(first) == pytest.approx(np.mean(np.abs(first.diagonal())), rel=1e-15)
    again = sp.csr_matrix(first.shape)  # the same pattern arrays, new values (as assembled)
    again.data, again.indices, again.indptr = (rng.standard_normal(first.nnz), first.indices,
                                               first.indptr)
    assert scale(again) == pytest.approx(np.mean(np.abs(again.diagonal())), rel=1e-15)
    holed = sp.csr_matrix(sp.diags(np.r_[0.0, 2.0, 4.0]))  # a zero diagonal entry not stored
    holed.eliminate_zeros()
    assert scale(holed) == pytest.approx(2.0)
    assert scale(sp.csr_matrix((3, 3))) == 1.0
    assert np.isnan(scale(sp.csr_matrix(np.diag([np.nan, 1.0]))))
