"""Run under ``mpiexec -n 2``: decomposed or distributed solve of a compressed plate.

Prints one ``RESULT {json}`` line on rank 0 comparing against the serial monolithic solve.
Exit codes: 0 ok, 2 solver failure on any rank (message on stderr). The environment variable
``DECOMP_FAIL_PATCH`` forces the patch solve of that patch to raise (failure test).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

import numpy as np

from meshes.errors import SolverError
from models.backend import MPI
from models.shell.energy import ShellEnergy, ShellParams
from solvers import inertia_shift
from solvers.decomposition.block import BlockOptions
from solvers.decomposition.demo import PlateCase, plate_problem
from solvers.decomposition.distributed import distributed_minimize
from solvers.decomposition.parallel import ParallelOptions, parallel_block_solve
from solvers.decomposition.patch_energy import ShellProblem
from solvers.decomposition.split_newton import SplitAugmentedSystem, SplitNewtonSolver
from solvers.linear import LinearSolverOptions
from solvers.multigrid import shifted_product
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver, minimize


def _args() -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--mode", choices=["block", "distributed", "split"], default="block")
    parser.add_argument("--exchange", choices=["client_server", "neighbour"],
                        default="neighbour")
    parser.add_argument("--method", choices=["jacobi", "gauss_seidel"], default="gauss_seidel")
    parser.add_argument("--backend", choices=["mumps", "superlu_dist"], default="mumps")
    parser.add_argument("--cells", type=int, default=12)
    parser.add_argument("--compression", type=float, default=0.07)
    parser.add_argument("--patches-per-rank", type=int, default=1)
    parser.add_argument("--max-outer", type=int, default=500)
    return parser.parse_args()


def _next_frame(problem: ShellProblem, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Target compressed 0.5 % more and the start moved with it (a warm-started frame)."""
    y = problem.target.copy()
    y[:, 0] = 0.5 + 0.995 * (y[:, 0] - 0.5)
    return y, x + (y - problem.target)


def _ritz_values() -> list[float]:
    """Record every Lanczos estimate of the shift ladder's restart (appended in call order)."""
    record: list[float] = []
    lowest = inertia_shift.lowest_ritz_value

    def recorded(*args: Any, **kwargs: Any) -> float:
        record.append(lowest(*args, **kwargs))
        return record[-1]
    inertia_shift.lowest_ritz_value = recorded  # type: ignore[assignment]
    return record


def _product_error(solver: SplitNewtonSolver, energy: ShellEnergy, x0: np.ndarray) -> float:
    """max |split (A + G^T G) v - serial (A + G^T G) v| / max |serial| for a seeded v."""
    v = np.random.default_rng(1).standard_normal(x0.size)
    ev = solver.energy.evaluate(x0)
    assert isinstance(solver.linear, SplitAugmentedSystem)
    split = solver.linear.hessian_product(ev, v)
    serial = shifted_product(energy.evaluate(x0), 0.0, v)
    return float(np.abs(split - serial).max() / np.abs(serial).max())


def _split(problem: ShellProblem, partition: np.ndarray, x0: np.ndarray, comm: MPI.Comm,
           ) -> tuple[np.ndarray, dict[str, float]]:
    """Stencil-split Newton with the low-rank penalty, two frames; this rank's share.

    The shift ladder's Lanczos restart is on (as in the product): both solves record their
    estimates.
    """
    energy = problem.energy()
    g0 = float(np.linalg.norm(energy.evaluate(x0, order=1).grad))
    options = ShellNewtonOptions(rtol=1e-8, gradient_scale=g0, inertia_restart=True)
    ritz = _ritz_values()
    solver = SplitNewtonSolver(problem, partition, options, comm)
    x, rep = solver.minimize(x0)
    y2, x2_start = _next_frame(problem, x)
    solver.set_target(y2)
    x2, rep2 = solver.minimize(x2_start)  # second frame: the analysis is reused
    ritz_split = list(ritz)
    ritz.clear()
    serial = ShellNewtonSolver(energy, options)  # the same two frames on one solver: its
    _, rep_serial = serial.minimize(x0)  # shift memory from frame 1 is the split solver's
    energy.set_target(y2)
    x2_ref, rep2_ref = serial.minimize(x2_start)
    energy.set_target(problem.target)
    ritz_serial = list(ritz)
    same = len(ritz_split) == len(ritz_serial)
    ritz_diff = float(np.abs(np.subtract(ritz_split, ritz_serial)).max()
                      / np.abs(ritz_serial).max()) if same and ritz_serial else float("inf")
    info = solver.info()
    entries = comm.gather(info.local_matrix_entries, root=0)
    owned = comm.allreduce(info.owned_vertices, op=MPI.SUM)
    return x, {"iterations": rep.iterations, "converged": rep.converged,
               "time_total": rep.time_total, "local_entries": entries,
               "owned_total": owned, "analyses": info.symbolic_analyses,
               "factorizations": rep.factorizations,
               "factorizations_serial": rep_serial.factorizations,
               "frame2_converged": rep2.converged,
               "frame2_iterations": rep2.iterations, "frame2_iterations_ref": rep2_ref.iterations,
               "frame2_energy_rel": abs(rep2.energy - rep2_ref.energy) / abs(rep2_ref.energy),
               "frame2_max_diff": float(np.abs(x2 - x2_ref).max()),
               "product_error": _product_error(solver, energy, x0),
               "ritz_count": len(ritz_split), "ritz_count_ref": len(ritz_serial),
               "ritz_diff": ritz_diff}


def _run(args: argparse.Namespace, comm: MPI.Comm) -> dict[str, float]:
    low_rank = ShellParams(penalty_hessian="low_rank") if args.mode == "split" else ShellParams()
    problem, partition, x0 = plate_problem(PlateCase(cells=args.cells, params=low_rank,
                                                        compression=args.compression))
    energy = problem.energy()
    g0 = float(np.linalg.norm(energy.evaluate(x0, order=1).grad))
    symmetric = "lu" if args.backend == "superlu_dist" else "cholesky"
    newton = ShellNewtonOptions(rtol=1e-8, gradient_scale=g0, linear=LinearSolverOptions(
        backend=args.backend, symmetric=symmetric))  # the serial reference uses the same solver
    x_ref, ref = minimize(energy, x0, newton)
    out: dict[str, float] = {"energy_ref": ref.energy}
    if args.mode == "split":
        x, extra = _split(problem, partition, x0, comm)
        out |= extra | {"iterations_ref": ref.iterations,
                        "factorizations_ref": ref.factorizations,
                        "serial_entries": _serial_entries(energy, x0)}
    elif args.mode == "distributed":
        x, rep = distributed_minimize(energy, x0, newton, comm)
        out |= {"iterations": rep.iterations, "iterations_ref": ref.iterations,
                "converged": rep.converged, "time_evaluate": rep.time_evaluate,
                "time_factorize": rep.time_factorize, "time_total": rep.time_total}
    else:
        fail = int(os.environ.get("DECOMP_FAIL_PATCH", "-1"))
        block = BlockOptions(method=args.method, rtol=1e-8, gradient_scale=g0, fail_patch=fail,
                             max_outer=args.max_outer)
        res = parallel_block_solve(problem, partition, x0, ParallelOptions(
            exchange=args.exchange, patches_per_rank=args.patches_per_rank, block=block), comm)
        x, rep_b = res.x, res.report
        out |= {"outer": rep_b.outer_iterations, "converged": rep_b.converged,
                "patches": res.patches.n_patches}
    energy_x = energy.value(x)
    spread = comm.allreduce(float(np.abs(x - comm.bcast(x, root=0)).max()), op=MPI.MAX)
    return out | {"energy": energy_x, "energy_rel": abs(energy_x - ref.energy) / abs(ref.energy),
                  "max_diff": float(np.abs(x - x_ref).max()), "rank_spread": spread}


def _serial_entries(energy: ShellEnergy, x0: np.ndarray) -> int:
    """Entries of the serial augmented matrix [[A, G^T], [G, -I]]."""
    ev = energy.evaluate(x0)
    assert ev.hess is not None and ev.penalty_factor is not None
    return int(ev.hess.nnz + 2 * ev.penalty_factor.nnz + ev.penalty_factor.shape[0])


def main() -> int:
    comm = MPI.COMM_WORLD
    args = _args()
    try:
        out = _run(args, comm)
    except SolverError as err:
        print(f"rank {comm.rank}: {err}", file=sys.stderr, flush=True)
        return 2
    except Exception as err:  # noqa: BLE001 - anything else must not hang the other rank
        print(f"rank {comm.rank}: unexpected {type(err).__name__}: {err}", file=sys.stderr,
              flush=True)
        comm.Abort(2)
    if comm.rank == 0:
        print("RESULT " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
