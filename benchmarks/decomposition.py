"""Decomposition vs. the whole on a warm-started frame: block Gauss-Seidel / Jacobi over MPI
against monolithic Newton (serial, and split by stencils over the ranks).

Run on 1 rank (``.venv/bin/python benchmarks/decomposition.py``) or on 2
(``.venv/bin/mpiexec -n 2 .venv/bin/python benchmarks/decomposition.py``).

The per-frame problem (stated in the output): a square plate held by the cluster penalty
(``--vertices-per-cluster`` vertices per cluster, low-rank penalty) to a target compressed
``--compression`` along x is wrinkled: its minimiser is the previous frame (prepared once by
grid sequencing with the split Newton solver, cached under ``.cache/decomposition/``). The new
frame's target is compressed ``--increment`` more; every method starts from the previous
minimiser moved with the target (the warm start of a frame loop) and solves to the same
global relative gradient tolerance 1e-8. For each size it measures

* serial monolithic Newton on rank 0 (augmented low-rank penalty, MUMPS LDL^T): the 1-rank
  reference and the optimum every other method is compared with;
* split monolithic Newton over all ranks (stencils split by rank, augmented system as a
  distributed MPIAIJ, MUMPS LDL^T);
* the distributed monolithic solve with the *assembled* penalty (only up to
  ``--assembled-max`` vertices: H^T H fills in);
* the decomposed solve, Gauss-Seidel and Jacobi x neighbour and client-server exchange, one
  patch per rank;
* (first size only, ``--studies``) outer iterations vs. patch count, vs. k_B / k_P (k_B
  scaled, each with its own prepared frame) and vs. the block options (Anderson off, forcing
  term eta, inexact inner solves of at most 2 Newton steps).

Per row: outer (Newton) iterations, final energy gap to the monolithic optimum, max vertex
difference (relative to the plate width), wall time (slowest rank), speedup over the serial
monolithic solve, peak resident memory of the ranks. Prints a table, a plain-language verdict
computed from the numbers, and writes ``benchmarks/results/decomposition_<size>.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from models.backend import MPI
from models.shell.energy import ShellParams
from solvers.decomposition.block import BlockOptions
from solvers.decomposition.demo import FrameCase, PlateCase, plate_frame, prepare_wrinkled
from solvers.decomposition.distributed import distributed_minimize
from solvers.decomposition.parallel import ParallelOptions, parallel_block_solve
from solvers.decomposition.patch_energy import ShellProblem
from solvers.decomposition.split_newton import SplitNewtonSolver, split_minimize
from solvers.shell_newton import ShellNewtonOptions, minimize

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
CACHE = ROOT / ".cache" / "decomposition"
RTOL = 1e-8
FRAME = ("warm-started frame: previous minimiser (plate wrinkled at {c:.1%} compression) "
         "moved with a target compressed {i:.1%} more; tolerance ||g|| <= 1e-8 ||g_0||")


def _args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[40_000, 160_000],
                        help="approximate vertex counts")
    parser.add_argument("--quick", action="store_true", help="one size of ~2.5k vertices")
    parser.add_argument("--compression", type=float, default=0.07)
    parser.add_argument("--increment", type=float, default=0.005)
    parser.add_argument("--vertices-per-cluster", type=int, default=9)
    parser.add_argument("--patches", type=int, nargs="+", default=[2, 4, 8, 16])
    parser.add_argument("--bending-scales", type=float, nargs="+", default=[0.1, 10.0],
                        help="k_B multipliers for the k_B / k_P study (1 is the main run)")
    parser.add_argument("--studies", nargs="*", default=["patches", "stiffness", "options"],
                        choices=["patches", "stiffness", "options"],
                        help="studies at the first size (none: --studies with no value)")
    parser.add_argument("--block", nargs="*", default=["gauss_seidel", "jacobi"],
                        choices=["gauss_seidel", "jacobi"], help="block methods of every size")
    parser.add_argument("--exchanges", nargs="*", default=["neighbour", "client_server"],
                        choices=["neighbour", "client_server"])
    parser.add_argument("--assembled-max", type=int, default=12_000,
                        help="largest size run with the assembled-penalty distributed solve")
    parser.add_argument("--max-outer", type=int, default=400)
    parser.add_argument("--split-icntl", nargs="*", default=[], metavar="I=V",
                        help="extra MUMPS ICNTL for a second split row, e.g. 28=2 29=2 "
                             "(parallel ordering); the default split row always runs")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    return parser.parse_args()


def _peak_mb(comm: Any) -> list[float]:
    """Peak resident memory of every rank so far, MB (ru_maxrss is in kB on Linux)."""
    return comm.allgather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)


def _timed(comm: Any, fn: Callable[[], Any]) -> tuple[Any, float]:
    """Run fn after a barrier; wall time up to the slowest rank."""
    comm.Barrier()
    start = time.perf_counter()
    out = fn()
    comm.Barrier()
    return out, time.perf_counter() - start


def _newton(g0: float) -> ShellNewtonOptions:
    """Newton options with the frame's fixed gradient scale."""
    return ShellNewtonOptions(rtol=RTOL, gradient_scale=g0)


def _grad_norm(problem: ShellProblem, x: np.ndarray) -> float:
    """||grad W(x)||."""
    grad = problem.energy().evaluate(x, order=1).grad
    assert grad is not None  # order 1
    return float(np.linalg.norm(grad))


def _prepare(comm: Any, fc: FrameCase) -> np.ndarray:
    """Previous frame's minimiser (grid sequencing, split Newton on all ranks), cached."""
    p = fc.plate
    path = CACHE / (f"frame_{p.cells}_{p.vertices_per_cluster}_{p.compression}_"
                    f"{p.params.k_L}_{p.params.k_B}_{p.params.k_P}.npz")
    if path.exists():
        return np.load(path)["x"]

    def solve(problem: ShellProblem, partition: np.ndarray, x0: np.ndarray) -> np.ndarray:
        return split_minimize(problem, x0, partition, _newton(_grad_norm(problem, x0)),
                              comm)[0]

    start = time.perf_counter()
    x = prepare_wrinkled(fc, solve)
    if comm.rank == 0:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, x=x)
        print(f"  prepared the previous frame in {time.perf_counter() - start:.1f} s "
              f"-> {path.relative_to(ROOT)}", flush=True)
    return x


class Frame:
    """One frame problem and its serial monolithic reference (computed on rank 0)."""

    def __init__(self, comm: Any, fc: FrameCase) -> None:
        self.comm, self.case = comm, fc
        x_prev = _prepare(comm, fc)
        self.problem, self.partition, self.x0 = plate_frame(fc, x_prev)
        self.g0 = _grad_norm(self.problem, self.x0)
        self.ref = self._monolithic()

    def _monolithic(self) -> dict[str, Any]:
        """Serial Newton on rank 0 (others wait); the reference optimum broadcast to all."""
        result = None
        self.comm.Barrier()
        if self.comm.rank == 0:
            start = time.perf_counter()
            x, rep = minimize(self.problem.energy(), self.x0,  # type: ignore[arg-type]
                              _newton(self.g0))
            result = (x, rep.energy, rep.iterations, rep.converged,
                      time.perf_counter() - start, rep.factorizations)
        x, w, its, ok, seconds, facts = self.comm.bcast(result, root=0)
        return {"x": x, "energy": w, "iterations": its, "converged": ok, "time": seconds,
                "factorizations": facts}

    @property
    def vertices(self) -> int:
        """Number of shell vertices."""
        return self.problem.topology.n_vertices

    def row(self, method: str, x: np.ndarray, seconds: float, **extra: Any) -> dict[str, Any]:
        """One table row against the monolithic reference (progress printed on rank 0)."""
        w = self.problem.energy().value(x)
        out = {"method": method, "vertices": self.vertices, **extra,
               "energy_gap": abs(w - self.ref["energy"]) / abs(self.ref["energy"]),
               "max_diff": float(np.abs(x - self.ref["x"]).max() / self.case.plate.width),
               "time": seconds, "speedup": self.ref["time"] / seconds,
               "peak_mb": _peak_mb(self.comm)}
        if self.comm.rank == 0:
            print(f"  {method}: {seconds:.2f} s outer={out.get('outer')} "
                  f"gap={out['energy_gap']:.1e}", flush=True)
        return out

    def reference_row(self) -> dict[str, Any]:
        """The serial monolithic row."""
        ref = self.ref
        return {"method": "serial monolithic (rank 0)", "vertices": self.vertices, "ranks": 1,
                "outer": ref["iterations"], "converged": ref["converged"],
                "factorizations": ref["factorizations"], "energy_gap": 0.0, "max_diff": 0.0,
                "time": ref["time"], "speedup": 1.0, "peak_mb": _peak_mb(self.comm)}


def _icntl(pairs: list[str]) -> tuple[tuple[int, int], ...]:
    """``["28=2", "29=2"]`` -> ``((28, 2), (29, 2))``."""
    return tuple((int(a), int(b)) for a, b in (p.split("=") for p in pairs))


def _split(frame: Frame, icntl: tuple[tuple[int, int], ...] = ()) -> dict[str, Any]:
    """Split monolithic Newton over all ranks (setup included in the time)."""
    newton = _newton(frame.g0)
    if icntl:
        linear = dataclasses.replace(newton.augmented_linear, mumps_icntl=icntl)
        newton = dataclasses.replace(newton, augmented_linear=linear)
    label = "" if not icntl else ", ICNTL " + " ".join(f"{i}={v}" for i, v in icntl)

    def run() -> tuple[np.ndarray, Any, Any, float]:
        start = time.perf_counter()
        solver = SplitNewtonSolver(frame.problem, frame.partition, newton, frame.comm)
        setup = time.perf_counter() - start
        x, rep = solver.minimize(frame.x0)
        return x, rep, solver.info(), setup

    (x, rep, info, setup), seconds = _timed(frame.comm, run)
    return frame.row(f"split monolithic (MUMPS LDL^T{label})", x, seconds, ranks=frame.comm.size,
                     outer=rep.iterations, converged=rep.converged, time_setup=setup,
                     factorizations=rep.factorizations, time_evaluate=rep.time_evaluate,
                     time_factorize=rep.time_factorize, time_analysis=rep.time_analysis,
                     symbolic_analyses=info.symbolic_analyses,
                     factor_memory_mb=list(info.factor_memory_mb))


def _assembled(frame: Frame) -> dict[str, Any]:
    """Monolithic Newton with the assembled penalty as MPIAIJ (redundant evaluation)."""
    params = replace(frame.problem.params, penalty_hessian="assembled")
    energy = replace(frame.problem, params=params).energy()
    (x, rep), seconds = _timed(frame.comm, lambda: distributed_minimize(
        energy, frame.x0, _newton(frame.g0), frame.comm))  # type: ignore[arg-type]
    return frame.row("distributed monolithic, assembled H^T H", x, seconds,
                     ranks=frame.comm.size, outer=rep.iterations, converged=rep.converged,
                     factorizations=rep.factorizations, time_factorize=rep.time_factorize)


def _block(frame: Frame, method: str, exchange: str, n_patches: int, max_outer: int,
           label: str = "", **block: Any) -> dict[str, Any]:
    """Decomposed solve with ``n_patches`` patches over the ranks."""
    comm = frame.comm
    opts = ParallelOptions(exchange=exchange,  # type: ignore[arg-type]
                           patches_per_rank=max(1, n_patches // comm.size),
                           block=BlockOptions(method=method,  # type: ignore[arg-type]
                                              rtol=RTOL, gradient_scale=frame.g0,
                                              max_outer=max_outer, **block))
    res, seconds = _timed(comm, lambda: parallel_block_solve(
        frame.problem, frame.partition, frame.x0, opts, comm))
    r = res.report
    return frame.row(f"block {method} ({exchange}){label}", res.x, seconds, ranks=comm.size,
                     patches=res.patches.n_patches, colours=r.colours, outer=r.outer_iterations,
                     converged=r.converged, inner=r.inner_iterations,
                     rejected_mixing=r.rejected_mixing, time_exchange=r.time_exchange,
                     time_patch_solves=r.time_solve)


def _main_rows(frame: Frame, args: argparse.Namespace) -> list[dict]:
    """Reference, split, assembled (small sizes), block methods x exchanges."""
    rows = [frame.reference_row(), _split(frame)]
    if args.split_icntl:
        rows.append(_split(frame, _icntl(args.split_icntl)))
    if frame.vertices <= args.assembled_max:
        rows.append(_assembled(frame))
    for method in args.block:
        for exchange in args.exchanges:
            rows.append(_block(frame, method, exchange, frame.comm.size, args.max_outer))
    return rows


def _patch_study(frame: Frame, args: argparse.Namespace) -> list[dict]:
    """Outer iterations vs. patch count (Gauss-Seidel, neighbour)."""
    return [_block(frame, "gauss_seidel", "neighbour", p, args.max_outer)
            | {"study": "patch count"}
            for p in args.patches if p % frame.comm.size == 0 and p != frame.comm.size]


def _options_study(frame: Frame, args: argparse.Namespace) -> list[dict]:
    """Effect of each block option (Gauss-Seidel, neighbour, one patch per rank)."""
    variants: list[tuple[str, dict[str, Any]]] = [
        (", no Anderson", {"anderson": 0}), (", eta 0.01", {"eta": 0.01}),
        (", eta 0.5", {"eta": 0.5}),
        (", inner <= 2 Newton steps", {"inner": ShellNewtonOptions(max_iterations=2)})]
    return [_block(frame, "gauss_seidel", "neighbour", frame.comm.size, args.max_outer,
                   label, **opts) | {"study": "block options"} for label, opts in variants]


def _stiffness_study(comm: Any, fc: FrameCase, args: argparse.Namespace) -> list[dict]:
    """Outer iterations vs. k_B / k_P (k_B scaled, own prepared frame), GS, neighbour."""
    rows = []
    for scale in args.bending_scales:
        params = replace(fc.plate.params, k_B=fc.plate.params.k_B * scale)
        frame = Frame(comm, replace(fc, plate=replace(fc.plate, params=params)))
        ratio = {"study": "k_B/k_P", "k_B_over_k_P": params.k_B / params.k_P}
        rows += [frame.reference_row() | ratio, _split(frame) | ratio,
                 _block(frame, "gauss_seidel", "neighbour", comm.size, args.max_outer) | ratio]
    return rows


def _table(rows: list[dict]) -> str:
    """Fixed-width table of the rows."""
    head = (f"{'method':56s} {'n':>7s} {'r':>2s} {'P':>3s} {'outer':>6s} {'conv':>5s} "
            f"{'gap':>9s} {'maxdiff':>9s} {'time s':>8s} {'speedup':>7s} {'MB/rank':>8s}  study")
    lines = [head, "-" * len(head)]
    for r in rows:
        study = r.get("study", "")
        if "k_B_over_k_P" in r:
            study += f" {r['k_B_over_k_P']:.0e}"
        lines.append(f"{r['method']:56s} {r['vertices']:7d} {r['ranks']:2d} "
                     f"{r.get('patches', '-')!s:>3s} {r['outer']!s:>6s} {r['converged']!s:>5s} "
                     f"{r['energy_gap']:9.2e} {r['max_diff']:9.2e} {r['time']:8.2f} "
                     f"{r['speedup']:7.2f} {max(r['peak_mb']):8.0f}  {study}")
    return "\n".join(lines)


def verdict(rows: list[dict], target: float = 1.6) -> str:
    """Plain-language 'which method wins where' from the main rows of one size.

    A method counts only if it converged with the same answer (energy gap <= 1e-8, max
    vertex difference <= 1e-6 of the width).
    """
    main = [r for r in rows if "study" not in r]
    same = [r for r in main if r["converged"] and r["energy_gap"] <= 1e-8
            and r["max_diff"] <= 1e-6]
    best = max(same, key=lambda r: r["speedup"])
    blocks = [r for r in main if r["method"].startswith("block")]
    parallel = [r for r in same if r["ranks"] > 1]
    text = (f"n={main[0]['vertices']}: fastest with the same answer is {best['method']} on "
            f"{best['ranks']} rank(s), {best['speedup']:.2f}x the serial monolithic solve")
    if parallel:
        top = max(parallel, key=lambda r: r["speedup"])
        met = "meets" if top["speedup"] >= target else "misses"
        text += (f"; the best parallel method ({top['method']}) {met} the {target}x target "
                 f"({top['speedup']:.2f}x)")
    if blocks:
        fastest = max(blocks, key=lambda r: r["speedup"])
        text += (f"; the best decomposition ({fastest['method']}) needs {fastest['outer']} "
                 f"outer iterations against {main[0]['outer']} Newton iterations and runs at "
                 f"{fastest['speedup']:.2f}x" + ("" if fastest["converged"] else
                                                  " without converging"))
    return text


def _frame_case(n: int, args: argparse.Namespace) -> FrameCase:
    """The frame of about n vertices."""
    plate = PlateCase(cells=max(8, round(np.sqrt(n)) - 1), compression=args.compression,
                      vertices_per_cluster=args.vertices_per_cluster,
                      params=ShellParams(penalty_hessian="low_rank"))
    return FrameCase(plate=plate, increment=args.increment, coarse_levels=2)


def _write(comm: Any, args: argparse.Namespace, n: int, rows: list[dict]) -> None:
    """Print the table and verdict; write decomposition_<n>.json (rank 0)."""
    if comm.rank != 0:
        return
    text = verdict(rows)
    frame = FRAME.format(c=args.compression, i=args.increment)
    print(frame)
    print(_table(rows))
    print("verdict: " + text)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    out = args.out_dir / f"decomposition_{n}.json"
    out.write_text(json.dumps({"ranks": comm.size, "sizes": [n], "frame": frame,
                               "verdict": text, "rows": rows}, indent=1))
    print(f"wrote {out}", flush=True)


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    args = _args()
    comm = MPI.COMM_WORLD
    sizes = [2_500] if args.quick else args.sizes
    for k, n in enumerate(sizes):
        fc = _frame_case(n, args)
        if comm.rank == 0:
            print(f"size {n}: {(fc.plate.cells + 1) ** 2} vertices, {comm.size} rank(s)",
                  flush=True)
        frame = Frame(comm, fc)
        rows = _main_rows(frame, args)
        if k == 0 and "patches" in args.studies:
            rows += _patch_study(frame, args)
        if k == 0 and "options" in args.studies:
            rows += _options_study(frame, args)
        if k == 0 and "stiffness" in args.studies:
            rows += _stiffness_study(comm, fc, args)
        _write(comm, args, (fc.plate.cells + 1) ** 2, rows)


if __name__ == "__main__":
    main()
