"""Decomposition vs. the whole: block Gauss-Seidel / Jacobi over MPI against monolithic Newton.

Run serially or under ``mpiexec -n 2 .venv/bin/python benchmarks/decomposition.py``. Problem:
a square plate held by the cluster penalty to a target compressed 7 % along x (it wrinkles),
``--vertices-per-cluster`` vertices per cluster (assembled penalty Hessian, so the three
methods share one Hessian). For each size it measures

* the serial monolithic Newton solve (rank 0; the reference optimum),
* the distributed monolithic solve (MPIAIJ + MUMPS over all ranks),
* the decomposed solve, both methods x both exchanges, one patch per rank,
* (first size only) outer iterations vs. patch count (2, 4, 8, 16, Gauss-Seidel, neighbour)
  and vs. k_B / k_P (k_B scaled, 4 patches),

reporting outer iterations, final energy gap to the monolithic optimum, max vertex
difference (relative to the plate width), wall time and speedup over the serial monolithic
solve. Prints a table and writes ``benchmarks/results/decomposition.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from models.backend import MPI
from models.shell.energy import ShellParams
from solvers.decomposition.block import BlockOptions
from solvers.decomposition.demo import PlateCase, plate_problem
from solvers.decomposition.distributed import distributed_minimize
from solvers.decomposition.parallel import (
    ParallelOptions,
    parallel_block_solve,
)
from solvers.shell_newton import ShellNewtonOptions, minimize

RESULTS = Path(__file__).resolve().parent / "results" / "decomposition.json"


def _args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[40_000, 160_000],
                        help="approximate vertex counts")
    parser.add_argument("--quick", action="store_true", help="one size of ~5k vertices")
    parser.add_argument("--patches", type=int, nargs="+", default=[2, 4, 8, 16])
    parser.add_argument("--bending-scales", type=float, nargs="+", default=[0.1, 1.0, 10.0],
                        help="k_B multipliers for the k_B / k_P study")
    parser.add_argument("--vertices-per-cluster", type=int, default=9)
    parser.add_argument("--max-outer", type=int, default=500)
    parser.add_argument("--out", type=Path, default=RESULTS)
    return parser.parse_args()


def _grad_norm(energy: Any, x: np.ndarray) -> float:
    """||grad W(x)||."""
    return float(np.linalg.norm(energy.evaluate(x, order=1).grad))


def _timed(comm: Any, fn: Any) -> tuple[Any, float]:
    """Run fn after a barrier; wall time up to the slowest rank."""
    comm.Barrier()
    start = time.perf_counter()
    out = fn()
    comm.Barrier()
    return out, time.perf_counter() - start


def _monolithic(comm: Any, case: PlateCase, newton: ShellNewtonOptions) -> dict[str, Any]:
    """Serial Newton on rank 0 (others wait); the reference optimum broadcast to all."""
    problem, _, x0 = plate_problem(case)
    energy = problem.energy()
    result = None
    comm.Barrier()
    start = time.perf_counter()
    if comm.rank == 0:
        x, rep = minimize(energy, x0, newton)  # type: ignore[arg-type]
        result = (x, rep.energy, rep.iterations, rep.converged, time.perf_counter() - start)
    x, w, its, ok, seconds = comm.bcast(result, root=0)
    return {"x": x, "energy": w, "iterations": its, "converged": ok, "time": seconds}


def _row(method: str, case: PlateCase, ref: dict[str, Any], x: np.ndarray, w: float,
         seconds: float, **extra: Any) -> dict[str, Any]:
    """One table row against the monolithic reference (progress printed on rank 0)."""
    if MPI.COMM_WORLD.rank == 0:
        print(f"  {method}: {seconds:.2f} s {extra}", flush=True)
    return {"method": method, "vertices": (case.cells + 1) ** 2, **extra,
            "energy_gap": abs(w - ref["energy"]) / abs(ref["energy"]),
            "max_diff": float(np.abs(x - ref["x"]).max() / case.width), "time": seconds,
            "speedup": ref["time"] / seconds}


def _distributed(comm: Any, case: PlateCase, newton: ShellNewtonOptions,
                 ref: dict[str, Any]) -> dict[str, Any]:
    """Monolithic Newton with the MPIAIJ Hessian on all ranks."""
    problem, _, x0 = plate_problem(case)
    energy = problem.energy()
    (x, rep), seconds = _timed(comm, lambda: distributed_minimize(
        energy, x0, newton, comm))  # type: ignore[arg-type]
    return _row("distributed monolithic (MUMPS)", case, ref, x, rep.energy, seconds,
                ranks=comm.size, outer=rep.iterations, converged=rep.converged,
                time_evaluate=rep.time_evaluate, time_factorize=rep.time_factorize)


def _block(comm: Any, case: PlateCase, ref: dict[str, Any], method: str, exchange: str,
           n_patches: int, g0: float, max_outer: int) -> dict[str, Any]:
    """Decomposed solve with ``n_patches`` patches over the ranks."""
    problem, partition, x0 = plate_problem(case)
    opts = ParallelOptions(exchange=exchange,  # type: ignore[arg-type]
                           patches_per_rank=max(1, n_patches // comm.size),
                           block=BlockOptions(method=method,  # type: ignore[arg-type]
                                              gradient_scale=g0, max_outer=max_outer))
    res, seconds = _timed(comm, lambda: parallel_block_solve(problem, partition, x0, opts, comm))
    w = problem.energy().value(res.x)
    r = res.report
    return _row(f"block {method} ({exchange})", case, ref, res.x, w, seconds, ranks=comm.size,
                patches=res.patches.n_patches, colours=r.colours, outer=r.outer_iterations,
                converged=r.converged, inner=r.inner_iterations,
                time_exchange=r.time_exchange, time_patch_solves=r.time_solve)


def _size(comm: Any, case: PlateCase, args: argparse.Namespace, first: bool) -> list[dict]:
    """Every measurement of one problem size."""
    problem, _, x0 = plate_problem(case)
    g0 = _grad_norm(problem.energy(), x0)
    newton = ShellNewtonOptions(rtol=1e-8, gradient_scale=g0)
    ref = _monolithic(comm, case, newton)
    rows = [{"method": "serial monolithic (rank 0)", "vertices": (case.cells + 1) ** 2,
             "ranks": 1, "outer": ref["iterations"], "converged": ref["converged"],
             "energy_gap": 0.0, "max_diff": 0.0, "time": ref["time"], "speedup": 1.0}]
    rows.append(_distributed(comm, case, newton, ref))
    for method in ("gauss_seidel", "jacobi"):
        for exchange in ("neighbour", "client_server"):
            rows.append(_block(comm, case, ref, method, exchange, comm.size, g0, args.max_outer))
    if first:
        rows += [_block(comm, case, ref, "gauss_seidel", "neighbour", p, g0, args.max_outer)
                 | {"study": "patch count"} for p in args.patches if p % comm.size == 0]
        rows += _stiffness_study(comm, case, args)
    return rows


def _stiffness_study(comm: Any, case: PlateCase, args: argparse.Namespace) -> list[dict]:
    """Outer iterations vs. k_B / k_P (k_B scaled), 4 patches, Gauss-Seidel, neighbour."""
    rows = []
    for scale in args.bending_scales:
        params = replace(case.params, k_B=case.params.k_B * scale)
        scaled = replace(case, params=params)
        problem, _, x0 = plate_problem(scaled)
        g0 = _grad_norm(problem.energy(), x0)
        ref = _monolithic(comm, scaled, ShellNewtonOptions(rtol=1e-8, gradient_scale=g0))
        row = _block(comm, scaled, ref, "gauss_seidel", "neighbour", 4, g0, args.max_outer)
        rows.append(row | {"study": "k_B/k_P", "k_B_over_k_P": params.k_B / params.k_P})
    return rows


def _table(rows: list[dict]) -> str:
    """Fixed-width table of the rows."""
    head = (f"{'method':34s} {'n':>7s} {'P':>3s} {'outer':>6s} {'conv':>5s} {'gap':>9s} "
            f"{'maxdiff':>9s} {'time s':>8s} {'speedup':>7s}  study")
    lines = [head, "-" * len(head)]
    for r in rows:
        study = r.get("study", "")
        if "k_B_over_k_P" in r:
            study += f" {r['k_B_over_k_P']:.0e}"
        lines.append(f"{r['method']:34s} {r['vertices']:7d} {r.get('patches', '-')!s:>3s} "
                     f"{r['outer']!s:>6s} {r['converged']!s:>5s} {r['energy_gap']:9.2e} "
                     f"{r['max_diff']:9.2e} {r['time']:8.2f} {r['speedup']:7.2f}  {study}")
    return "\n".join(lines)


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    args = _args()
    comm = MPI.COMM_WORLD
    sizes = [5_000] if args.quick else args.sizes
    rows: list[dict] = []
    for k, n in enumerate(sizes):
        case = PlateCase(cells=max(2, round(np.sqrt(n)) - 1), compression=0.07,
                         vertices_per_cluster=args.vertices_per_cluster, params=ShellParams())
        rows += _size(comm, case, args, first=k == 0)
    if comm.rank == 0:
        print(_table(rows))
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"ranks": comm.size, "sizes": sizes, "rows": rows},
                                       indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
