"""Wall-time cap of the block (decomposed) solve: ``BlockOptions.max_seconds``.

Serial (``SerialExchange``) and on 2 ranks: the outer loop stops unconverged by the cap, and
every rank stops after the same outer iteration even when the ranks' clocks disagree (the
decision is agreed through the exchange). Run as a script under ``mpiexec -n 2`` it prints one
``RESULT {json}`` line on rank 0 (the MPI test below does that).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import pytest

from meshes.errors import InputError
from solvers.decomposition.block import BlockOptions, extrapolate_outer, serial_block_solve
from solvers.decomposition.demo import PlateCase, plate_problem
from solvers.decomposition.patch_energy import PatchEnergy, ShellProblem
from solvers.decomposition.patches import build_patches

WRINKLED = PlateCase(cells=12, compression=0.07)  # 169 vertices; Jacobi needs > 100 outer its
CAP = 0.5  # s; a 169-vertex outer iteration takes ~0.01-0.05 s


def _grad_norm(problem: ShellProblem, x: np.ndarray) -> float:
    """||grad W(x)||."""
    grad = problem.energy().evaluate(x, order=1).grad
    assert grad is not None  # order 1
    return float(np.linalg.norm(grad))


def _serial(n_parts: int = 4) -> tuple[list[PatchEnergy], np.ndarray, float]:
    problem, partition, x0 = plate_problem(WRINKLED)
    g0 = _grad_norm(problem, x0)
    patches = build_patches(problem.topology, partition, n_parts)
    return [PatchEnergy(problem, p.interior) for p in patches.patches], x0, g0


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan")])
def test_max_seconds_must_be_positive(value: float) -> None:
    with pytest.raises(InputError, match="BlockOptions.max_seconds"):
        BlockOptions(max_seconds=value)


def test_serial_solve_stops_by_the_cap_unconverged() -> None:
    energies, x0, g0 = _serial()
    opts = BlockOptions(method="jacobi", rtol=1e-8, gradient_scale=g0, max_seconds=CAP)
    x, rep = serial_block_solve(energies, x0, opts)
    per_outer = rep.time_total / rep.outer_iterations
    print(f"stopped_by={rep.stopped_by} outer={rep.outer_iterations} "
          f"time={rep.time_total:.3f} s ({per_outer:.4f} s per outer) "
          f"|g|/|g0|={rep.grad_norm / g0:.2e}")
    assert rep.stopped_by == "max_seconds"
    assert not rep.converged and rep.grad_norm > rep.tolerance
    assert 1 <= rep.outer_iterations < opts.max_outer
    assert len(rep.grad_history) == rep.outer_iterations + 1
    # stops after the first outer iteration that ends past the cap: overshoot < 1 iteration
    # (plus the final gradient evaluation)
    assert CAP < rep.time_total < CAP + 3 * per_outer
    # the cap only truncates: the same number of outer iterations without a cap is bitwise
    # the same iterate (the extra reduction changes nothing)
    uncapped = BlockOptions(method="jacobi", rtol=1e-8, gradient_scale=g0,
                            max_outer=rep.outer_iterations)
    x2, rep2 = serial_block_solve(energies, x0, uncapped)
    assert rep2.stopped_by == "max_outer"
    assert rep2.grad_history == rep.grad_history
    assert np.array_equal(x2, x)


def test_generous_cap_changes_nothing_and_reports_tolerance() -> None:
    energies, x0, g0 = _serial()
    base = BlockOptions(method="gauss_seidel", rtol=1e-8, gradient_scale=g0)
    x_inf, rep_inf = serial_block_solve(energies, x0, base)
    x_cap, rep_cap = serial_block_solve(energies, x0, BlockOptions(
        method="gauss_seidel", rtol=1e-8, gradient_scale=g0, max_seconds=1e6))
    print(f"outer={rep_cap.outer_iterations} stopped_by={rep_cap.stopped_by}")
    assert rep_inf.converged and rep_inf.stopped_by == rep_cap.stopped_by == "tolerance"
    assert rep_cap.grad_history == rep_inf.grad_history
    assert np.array_equal(x_cap, x_inf)


def test_extrapolation_recovers_a_geometric_rate_and_ignores_the_early_half() -> None:
    """||g_k|| = 0.5^k for 10 iterations, then 0.9 per iteration: the fit sees only 0.9."""
    history = [0.5**k for k in range(11)] + [0.5**10 * 0.9**k for k in range(1, 11)]
    rate, outer = extrapolate_outer(history, 1e-8)
    expected = 10 + (np.log10(1e-8) - 10 * np.log10(0.5)) / np.log10(0.9)  # 119.05
    print(f"rate={rate:.15f} outer={outer:.6f} expected={expected:.6f}")
    assert rate == pytest.approx(0.9, rel=1e-12)
    assert outer == pytest.approx(expected, rel=1e-12)
    assert extrapolate_outer([1.0, 1.0, 1.1, 1.2], 1e-8)[1] == np.inf  # no decrease
    assert extrapolate_outer([1.0, 1e-9], 1e-8)[1] == 1.0  # converged: its own count
    assert np.isnan(extrapolate_outer([1.0, 0.5], 1e-8)[1])  # too short to fit


@pytest.mark.mpi
@pytest.mark.parametrize("exchange", ["neighbour", "client_server"])
def test_two_ranks_stop_after_the_same_outer_iteration(mpiexec, exchange: str) -> None:
    """Rank 0's cap is SKEW s later (as if its clock lagged): the ranks still stop together."""
    proc = mpiexec([__file__, "--exchange", exchange], n=2, timeout=180)
    assert proc.returncode == 0, f"rc={proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    out = json.loads(next(ln for ln in proc.stdout.splitlines()
                          if ln.startswith("RESULT "))[len("RESULT "):])
    print(exchange, out)
    assert out["stopped_by"] == ["max_seconds", "max_seconds"]
    assert out["converged"] == [False, False]
    assert out["outer"][0] == out["outer"][1] >= 1
    assert out["grad_reduction"][0] == out["grad_reduction"][1] > 1e-8
    assert out["rank_spread"] == 0.0
    # rank 1 passed its cap; rank 0 stopped with it, well before its own (later) cap, which
    # a local decision would have waited for
    assert out["time_total"][1] > CAP
    assert out["time_total"][0] < CAP + SKEW / 2


# --- run under mpiexec -n 2 ---------------------------------------------------------------------

SKEW = 5.0  # s: rank 0's cap is CAP + SKEW, rank 1's is CAP (a margin of outer iterations
#             that take 0.5 s on a loaded machine)


def _mpi_main() -> int:
    from models.backend import MPI
    from solvers.decomposition.parallel import ParallelOptions, parallel_block_solve

    parser = argparse.ArgumentParser()
    parser.add_argument("--exchange", choices=["neighbour", "client_server"], default="neighbour")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    problem, partition, x0 = plate_problem(WRINKLED)
    g0 = _grad_norm(problem, x0)
    cap = CAP + SKEW if comm.rank == 0 else CAP  # the same as a clock skew of SKEW
    block = BlockOptions(method="jacobi", rtol=1e-8, gradient_scale=g0, max_seconds=cap)
    res = parallel_block_solve(problem, partition, x0, ParallelOptions(
        exchange=args.exchange, block=block), comm)
    rep = res.report
    mine = (rep.outer_iterations, rep.stopped_by, rep.converged, rep.time_total,
            rep.grad_norm / g0)
    every = comm.gather(mine, root=0)
    spread = comm.allreduce(float(np.abs(res.x - comm.bcast(res.x, root=0)).max()), op=MPI.MAX)
    if every is not None:  # rank 0
        keys = ("outer", "stopped_by", "converged", "time_total", "grad_reduction")
        out = {k: [r[i] for r in every] for i, k in enumerate(keys)} | {"rank_spread": spread}
        print("RESULT " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(_mpi_main())
