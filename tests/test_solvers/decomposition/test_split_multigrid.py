"""The distributed multigrid Newton system (solvers/decomposition/split_multigrid.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import shellcases  # noqa: E402

from meshes.errors import InputError  # noqa: E402
from meshes.shells import grid_plate  # noqa: E402
from models.backend import MPI  # noqa: E402
from models.embedding.clusters import ClusterOptions, build_clusters  # noqa: E402
from solvers.decomposition.patch_energy import ShellProblem  # noqa: E402
from solvers.decomposition.split_multigrid import LevelNumbering, level_owners  # noqa: E402
from solvers.decomposition.split_newton import SplitNewtonSolver  # noqa: E402
from solvers.multigrid import MultigridOptions, ShellHierarchy  # noqa: E402
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver  # noqa: E402

SCRIPT = "tests/split_multigrid_mpi_case.py"


def test_every_coarse_vertex_goes_to_the_owner_of_its_place_on_the_finer_level() -> None:
    hier = ShellHierarchy.build(*grid_plate(3, 3), levels=2)
    fine_owner = (hier.vertices[:, 0] > 0.5).astype(np.int64)  # two halves of the plate
    owners = level_owners(fine_owner, hier.prolongations())
    assert [o.size for o in owners] == list(hier.level_sizes)
    np.testing.assert_array_equal(owners[-1], fine_owner)
    for level in range(len(owners) - 1):
        s = hier.subdivision.matrices[level].tocsc()
        for j in range(s.shape[1]):  # the finer vertex at the same place has weight 1
            rows = s.indices[s.indptr[j]: s.indptr[j + 1]]
            same = rows[np.isclose(s.data[s.indptr[j]: s.indptr[j + 1]], 1.0)]
            assert same.size == 1 and owners[level][j] == owners[level + 1][same[0]]


@pytest.mark.parametrize("size", [1, 2, 3])
def test_level_numbering_gives_every_dof_one_row_inside_its_rank(size: int) -> None:
    owner = np.random.default_rng(size).integers(0, size, 40)
    numberings = [LevelNumbering.build(owner, r, size) for r in range(size)]
    dof = numberings[0].dof
    assert np.array_equal(np.sort(dof), np.arange(120))
    for r, n in enumerate(numberings):
        rows = dof[n.owned]
        assert np.array_equal(rows, np.arange(n.offsets[r], n.offsets[r + 1]))
        assert np.all(owner[n.owned // 3] == r)


@pytest.mark.parametrize("growth", [1, 8])
def test_one_rank_split_multigrid_takes_the_serial_multigrid_steps(growth: int) -> None:
    """On one rank the split Newton with the distributed multigrid is the serial multigrid
    Newton (same CG, same steps): the same iterations, CG counts and minimiser; also with
    shifted steps lengthened (the large shells' default, ``step_growth``)."""
    hier = ShellHierarchy.build(*grid_plate(5, 5), levels=2)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=20)
    clusters = build_clusters(hier.vertices, hier.faces, ClusterOptions(count=20))
    options = ShellNewtonOptions(
        rtol=1e-9, hessian="exact", far_hessian="gauss_newton", linear_method="multigrid",
        gradient_scale=float(np.linalg.norm(energy.evaluate(x0, order=1).grad)),
        step_growth=growth,
        multigrid=MultigridOptions(forcing="eisenstat_walker", rtol=1e-4, fallback=False))
    serial = ShellNewtonSolver(energy, options, hierarchy=hier)
    x_ref, ref = serial.minimize(x0)
    problem = ShellProblem(energy.topology, energy.rest, energy.params, clusters.H,
                           energy.target)
    split = SplitNewtonSolver(problem, clusters.partition, options, MPI.COMM_SELF,
                              prolongations=hier.prolongations())
    x, rep = split.minimize(x0)
    print(ref.summary(), "|", rep.summary())
    assert rep.converged and rep.iterations == ref.iterations
    assert rep.krylov_iterations == ref.krylov_iterations
    assert np.abs(x - x_ref).max() < 1e-12
    assert np.abs(x_ref[:, 2]).max() > 0.01  # it wrinkles
    assert split.options.linear_method == "multigrid"
    assert any(it.step > 1.0 for it in rep.history) == (growth > 1)


def test_the_split_multigrid_refuses_a_smoother_without_a_distributed_form() -> None:
    """SOR has no parallel form on the fine level's 3 x 3 SBAIJ blocks: a clear error."""
    hier = ShellHierarchy.build(*grid_plate(3, 3), levels=1)
    energy, _ = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=4)
    clusters = build_clusters(hier.vertices, hier.faces, ClusterOptions(count=4))
    problem = ShellProblem(energy.topology, energy.rest, energy.params, clusters.H,
                           energy.target)
    options = ShellNewtonOptions(linear_method="multigrid", multigrid=MultigridOptions(
        smoother_pc="sor", eigen_estimate="setup"))
    with pytest.raises(InputError, match="smoother_pc: 'sor' has no distributed form"):
        SplitNewtonSolver(problem, clusters.partition, options, MPI.COMM_SELF,
                          prolongations=hier.prolongations())


def _result(proc) -> dict:
    assert proc.returncode == 0, f"rc={proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT "))
    return json.loads(line[len("RESULT "):])


PRODUCT = ["--phase-space", "--eigen-estimate", "solve", "--forcing", "eisenstat_walker",
           "--rtol", "1e-4"]
"""The multigrid settings the scenes use (``wrinkles.shell_setup.SCENE_DEFAULTS``)."""


@pytest.mark.mpi
@pytest.mark.parametrize(("ranks", "grid", "levels", "extra", "coarse_pc"),
                         [(2, 27, 1, [], "gamg"), (3, 27, 1, [], "gamg"),
                          (2, 20, 1, [], "redundant"), (2, 27, 2, ["--phase-space"], "gamg"),
                          (2, 27, 2, [], "redundant")])
def test_ranks_run_a_large_coarse_level_as_one_distributed_amg_cycle(
        mpiexec, ranks: int, grid: int, levels: int, extra: list[str], coarse_pc: str) -> None:
    """A 27 x 27 plate subdivided once: the coarse level (2 352 unknowns, from
    ``COARSE_AMG_FROM``) is one GAMG cycle over the ranks' own rows, not a Cholesky repeated
    whole on every rank; a 20 x 20 plate's coarse level (1 323) stays a Cholesky held whole by
    every rank (``PCREDUNDANT``). Subdivided twice, the large coarse level is a GAMG cycle
    when the phase space deflates the CG and a redundant Cholesky when it does not (the
    two-way joint CG's V-cycle). CG to 1e-8 reaches the direct solve's step either way
    (measured gap 1.4e-7 on 2 ranks, 233 CG iterations, at one level; 3.0e-7 and 286 at two,
    1.2e-8 and 18 with the Cholesky; the redundant cycle took 226 at one)."""
    out = _result(mpiexec([SCRIPT, "--grid", str(grid), "--levels", str(levels),
                           "--one-step", "0", *extra], n=ranks, timeout=180))
    print(out)
    assert out["ranks"] == ranks and out["coarse_pc"] == coarse_pc
    assert out["gap"] < 1e-5


@pytest.mark.mpi
@pytest.mark.parametrize(("ranks", "extra"), [(2, []), (3, []), (2, PRODUCT), (3, PRODUCT)])
def test_ranks_take_the_serial_multigrid_newton_steps(mpiexec, ranks: int, extra) -> None:
    """The wrinkling plate on 2 and 3 ranks, with CG to 1e-8 and with the scenes' settings
    (phase space, Eisenstat-Walker forcing, bounds once per solve): the serial minimiser,
    Newton iterations within one, the distributed operator equal to the serial ``A + G^T G``
    (measured 4.5e-16; the same 38 and 21 iterations; the CG counts differ by round-off,
    1067-1071 against 1072); the coarse levels moved to another shift equal to new products
    (measured 0 to 2e-18; 6.7e-5 with the shift halved); the level below the fine one,
    summed over the ranks' Hessian rows, equal to the serial ``P^T (A + tau I) P`` (measured
    5e-16; 0.11 without the received rows); with the phase space its ``A_Z`` equal to the
    serial one (measured 4e-16; 5e-5 with the penalty part 1 % off, where the CG counts
    still agree)."""
    out = _result(mpiexec([SCRIPT, *extra], n=ranks, timeout=180))
    print(out)
    assert out["ranks"] == ranks and out["converged"]
    assert abs(out["iterations"] - out["iterations_ref"]) <= 1
    assert out["max_diff"] < 1e-7 and out["energy_rel"] < 1e-12
    assert out["operator_rel"] < 1e-12 and out["shift_rel"] < 1e-13
    assert out["galerkin_rel"] < 1e-13 and out["phase_rel"] < 1e-13
    assert out["rank_spread"] == 0.0 and out["wrinkle"] > 0.01
