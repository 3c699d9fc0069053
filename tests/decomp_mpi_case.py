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

import numpy as np

from models.backend import MPI
from models.errors import SolverError
from solvers.decomposition.block import BlockOptions
from solvers.decomposition.demo import PlateCase, plate_problem
from solvers.decomposition.distributed import distributed_minimize
from solvers.decomposition.parallel import ParallelOptions, parallel_block_solve
from solvers.linear import LinearSolverOptions
from solvers.shell_newton import ShellNewtonOptions, minimize


def _args() -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--mode", choices=["block", "distributed"], default="block")
    parser.add_argument("--exchange", choices=["client_server", "neighbour"],
                        default="neighbour")
    parser.add_argument("--method", choices=["jacobi", "gauss_seidel"], default="gauss_seidel")
    parser.add_argument("--backend", choices=["mumps", "superlu_dist"], default="mumps")
    parser.add_argument("--cells", type=int, default=12)
    parser.add_argument("--compression", type=float, default=0.07)
    parser.add_argument("--patches-per-rank", type=int, default=1)
    return parser.parse_args()


def _run(args: argparse.Namespace, comm: MPI.Comm) -> dict[str, float]:
    problem, partition, x0 = plate_problem(PlateCase(cells=args.cells,
                                                        compression=args.compression))
    energy = problem.energy()
    g0 = float(np.linalg.norm(energy.evaluate(x0, order=1).grad))
    symmetric = "lu" if args.backend == "superlu_dist" else "cholesky"
    newton = ShellNewtonOptions(rtol=1e-8, gradient_scale=g0, linear=LinearSolverOptions(
        backend=args.backend, symmetric=symmetric))  # the serial reference uses the same solver
    x_ref, ref = minimize(energy, x0, newton)
    out: dict[str, float] = {"energy_ref": ref.energy}
    if args.mode == "distributed":
        x, rep = distributed_minimize(energy, x0, newton, comm)
        out |= {"iterations": rep.iterations, "iterations_ref": ref.iterations,
                "converged": rep.converged, "time_evaluate": rep.time_evaluate,
                "time_factorize": rep.time_factorize, "time_total": rep.time_total}
    else:
        fail = int(os.environ.get("DECOMP_FAIL_PATCH", "-1"))
        block = BlockOptions(method=args.method, rtol=1e-8, gradient_scale=g0, fail_patch=fail)
        res = parallel_block_solve(problem, partition, x0, ParallelOptions(
            exchange=args.exchange, patches_per_rank=args.patches_per_rank, block=block), comm)
        x, rep_b = res.x, res.report
        out |= {"outer": rep_b.outer_iterations, "converged": rep_b.converged,
                "patches": res.patches.n_patches}
    energy_x = energy.value(x)
    spread = comm.allreduce(float(np.abs(x - comm.bcast(x, root=0)).max()), op=MPI.MAX)
    return out | {"energy": energy_x, "energy_rel": abs(energy_x - ref.energy) / abs(ref.energy),
                  "max_diff": float(np.abs(x - x_ref).max()), "rank_spread": spread}


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
