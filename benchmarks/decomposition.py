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
difference (relative to the plate width), final gradient reduction ``||g|| / ||g_0||`` (of the
row's final state), wall time (slowest rank), speedup over the serial monolithic solve, peak
resident memory of the ranks. Prints a table, a plain-language verdict computed from the
numbers, and writes ``benchmarks/results/decomposition_<size>.json`` (``--out-dir``).

Block runs can be capped in wall time (``--block-seconds``, ``--study-seconds``:
``BlockOptions.max_seconds``, the outer loop only; the patch set-up is not capped). A capped
run stops unconverged (``stopped_by = "max_seconds"``); its row then carries the fitted
per-outer-iteration rate of ``||g||`` over the last half of its history and the outer
iterations and time that rate would need to reach the tolerance (``extrapolated_outer``,
``extrapolated_time``: an extrapolation, not a measurement; see
:func:`solvers.decomposition.block.extrapolate_outer`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from models.backend import MPI
from models.shell.energy import ShellParams
from solvers.decomposition.block import BlockOptions, BlockReport, extrapolate_outer
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
    parser.add_argument("--block-seconds", type=float, default=float("inf"),
                        help="wall-time cap (s) of the outer loop of every block run "
                             "(BlockOptions.max_seconds); default: no cap")
    parser.add_argument("--study-seconds", type=float, default=None,
                        help="cap of the block runs of the studies (default: --block-seconds)")
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
                "factorizations": facts, "grad_reduction": _grad_norm(self.problem, x) / self.g0}

    @property
    def vertices(self) -> int:
        """Number of shell vertices."""
        return self.problem.topology.n_vertices

    def row(self, method: str, x: np.ndarray, seconds: float, **extra: Any) -> dict[str, Any]:
        """One table row against the monolithic reference (progress printed on rank 0)."""
        w = self.problem.energy().value(x)
        out = {"method": method, "vertices": self.vertices, **extra,
               "grad_reduction": _grad_norm(self.problem, x) / self.g0,
               "energy_gap": abs(w - self.ref["energy"]) / abs(self.ref["energy"]),
               "max_diff": float(np.abs(x - self.ref["x"]).max() / self.case.plate.width),
               "time": seconds, "speedup": self.ref["time"] / seconds,
               "peak_mb": _peak_mb(self.comm)}
        if self.comm.rank == 0:
            print(f"  {method}: {seconds:.2f} s outer={out.get('outer')} "
                  f"g/g0={out['grad_reduction']:.1e} gap={out['energy_gap']:.1e}", flush=True)
        return out

    def reference_row(self) -> dict[str, Any]:
        """The serial monolithic row."""
        ref = self.ref
        return {"method": "serial monolithic (rank 0)", "vertices": self.vertices, "ranks": 1,
                "outer": ref["iterations"], "converged": ref["converged"],
                "stopped_by": "tolerance" if ref["converged"] else "not converged",
                "factorizations": ref["factorizations"],
                "grad_reduction": ref["grad_reduction"], "energy_gap": 0.0, "max_diff": 0.0,
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
                     outer=rep.iterations, converged=rep.converged,
                     stopped_by="tolerance" if rep.converged else "not converged",
                     time_setup=setup,
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
                     stopped_by="tolerance" if rep.converged else "not converged",
                     factorizations=rep.factorizations, time_factorize=rep.time_factorize)


def _extrapolation(r: BlockReport, seconds: float) -> dict[str, Any]:
    """Fitted rate per outer iteration; outer iterations and wall time it would need.

    Time = the row's set-up (wall minus outer loop) + the loop time per outer iteration times
    the extrapolated outer iterations. Non-finite values are written as None (JSON).
    """
    rate, outer = extrapolate_outer(r.grad_history, r.tolerance)
    loop = r.time_total / max(r.outer_iterations, 1)
    total = seconds - r.time_total + loop * outer
    return {k: (float(v) if np.isfinite(v) else None) for k, v in
            (("fitted_rate", rate), ("extrapolated_outer", outer), ("extrapolated_time", total))}


def _block(frame: Frame, method: str, exchange: str, n_patches: int, args: argparse.Namespace,
           label: str = "", study: bool = False, **block: Any) -> dict[str, Any]:
    """Decomposed solve with ``n_patches`` patches over the ranks, capped in wall time."""
    comm = frame.comm
    cap = args.study_seconds if study and args.study_seconds is not None else args.block_seconds
    opts = ParallelOptions(exchange=exchange,  # type: ignore[arg-type]
                           patches_per_rank=max(1, n_patches // comm.size),
                           block=BlockOptions(method=method,  # type: ignore[arg-type]
                                              rtol=RTOL, gradient_scale=frame.g0,
                                              max_outer=args.max_outer, max_seconds=cap,
                                              **block))
    res, seconds = _timed(comm, lambda: parallel_block_solve(
        frame.problem, frame.partition, frame.x0, opts, comm))
    r = res.report
    extra = {} if r.converged else _extrapolation(r, seconds)
    return frame.row(f"block {method} ({exchange}){label}", res.x, seconds, ranks=comm.size,
                     patches=res.patches.n_patches, colours=r.colours, outer=r.outer_iterations,
                     converged=r.converged, stopped_by=r.stopped_by,
                     max_seconds=cap if np.isfinite(cap) else None,
                     inner=r.inner_iterations, rejected_mixing=r.rejected_mixing,
                     time_outer_loop=r.time_total, time_exchange=r.time_exchange,
                     time_patch_solves=r.time_solve, grad_history=list(r.grad_history),
                     **extra)


def _main_rows(frame: Frame, args: argparse.Namespace) -> list[dict]:
    """Reference, split, assembled (small sizes), block methods x exchanges."""
    rows = [frame.reference_row(), _split(frame)]
    if args.split_icntl:
        rows.append(_split(frame, _icntl(args.split_icntl)))
    if frame.vertices <= args.assembled_max:
        rows.append(_assembled(frame))
    for method in args.block:
        for exchange in args.exchanges:
            rows.append(_block(frame, method, exchange, frame.comm.size, args))
    return rows


def _patch_study(frame: Frame, args: argparse.Namespace) -> list[dict]:
    """Outer iterations vs. patch count (Gauss-Seidel, neighbour)."""
    return [_block(frame, "gauss_seidel", "neighbour", p, args, study=True)
            | {"study": "patch count"}
            for p in args.patches if p % frame.comm.size == 0 and p != frame.comm.size]


def _options_study(frame: Frame, args: argparse.Namespace) -> list[dict]:
    """Effect of each block option (Gauss-Seidel, neighbour, one patch per rank)."""
    variants: list[tuple[str, dict[str, Any]]] = [
        (", no Anderson", {"anderson": 0}), (", eta 0.01", {"eta": 0.01}),
        (", eta 0.5", {"eta": 0.5}),
        (", inner <= 2 Newton steps", {"inner": ShellNewtonOptions(max_iterations=2)})]
    return [_block(frame, "gauss_seidel", "neighbour", frame.comm.size, args, label,
                   study=True, **opts) | {"study": "block options"} for label, opts in variants]


def _stiffness_study(comm: Any, fc: FrameCase, args: argparse.Namespace) -> list[dict]:
    """Outer iterations vs. k_B / k_P (k_B scaled, own prepared frame), GS, neighbour."""
    rows = []
    for scale in args.bending_scales:
        params = replace(fc.plate.params, k_B=fc.plate.params.k_B * scale)
        frame = Frame(comm, replace(fc, plate=replace(fc.plate, params=params)))
        ratio = {"study": "k_B/k_P", "k_B_over_k_P": params.k_B / params.k_P}
        rows += [frame.reference_row() | ratio, _split(frame) | ratio,
                 _block(frame, "gauss_seidel", "neighbour", comm.size, args, study=True)
                 | ratio]
    return rows


EXTRAPOLATION_NOTE = ("ext.outer / ext.time: outer iterations and wall time to reach the "
                      "tolerance, extrapolated from the fitted log-linear rate of ||g|| over "
                      "the last half of an unconverged run (not measured)")


def _opt(value: Any, spec: str, width: int = 0) -> str:
    """Format an optional number ('-' right-aligned to ``width`` when absent)."""
    return "-".rjust(width) if value is None else format(value, spec)


def _table(rows: list[dict]) -> str:
    """Fixed-width table of the rows (and the note on the extrapolated columns)."""
    head = (f"{'method':56s} {'n':>7s} {'r':>2s} {'P':>3s} {'outer':>6s} {'conv':>5s} "
            f"{'stopped by':>12s} {'g/g0':>8s} {'gap':>9s} {'maxdiff':>9s} {'time s':>8s} "
            f"{'speedup':>7s} {'ext.outer':>9s} {'ext.time':>9s} {'MB/rank':>8s}  study")
    lines = [head, "-" * len(head)]
    for r in rows:
        study = r.get("study", "")
        if "k_B_over_k_P" in r:
            study += f" {r['k_B_over_k_P']:.0e}"
        lines.append(f"{r['method']:56s} {r['vertices']:7d} {r['ranks']:2d} "
                     f"{r.get('patches', '-')!s:>3s} {r['outer']!s:>6s} {r['converged']!s:>5s} "
                     f"{r.get('stopped_by', '-'):>12s} {_opt(r.get('grad_reduction'), '8.1e', 8)} "
                     f"{r['energy_gap']:9.2e} {r['max_diff']:9.2e} {r['time']:8.2f} "
                     f"{r['speedup']:7.2f} {_opt(r.get('extrapolated_outer'), '9.0f', 9)} "
                     f"{_opt(r.get('extrapolated_time'), '9.0f', 9)} {max(r['peak_mb']):8.0f}  "
                     f"{study}")
    return "\n".join(lines + [EXTRAPOLATION_NOTE])


def how_far(r: dict[str, Any], reference: float) -> str:
    """'How far it got' of an unconverged block row, with its labelled extrapolation."""
    text = (f"{r['method']} stopped by {r['stopped_by']} without converging: ||g||/||g_0|| = "
            f"{r['grad_reduction']:.1e} after {r['outer']} outer iterations in {r['time']:.0f} s")
    if r.get("extrapolated_outer") is None:
        rate = r.get("fitted_rate")
        return text + (" (no decrease to extrapolate from: fitted rate "
                       f"{rate:.4f} per outer iteration)" if rate is not None else "")
    return text + (f"; extrapolation from its fitted rate ({r['fitted_rate']:.4f} per outer "
                   f"iteration over the last half): about {r['extrapolated_outer']:.0f} outer "
                   f"iterations and {r['extrapolated_time']:.0f} s to reach 1e-8 (extrapolated "
                   f"speedup {reference / r['extrapolated_time']:.3f}x)")


def study_summary(rows: list[dict]) -> str:
    """One clause per study row: how far it got or its outer iterations."""
    parts = []
    for r in (r for r in rows if r.get("study") and r["method"].startswith("block")):
        what = (f"patch count P={r['patches']}" if r["study"] == "patch count" else
                f"k_B/k_P={r['k_B_over_k_P']:.0e}" if "k_B_over_k_P" in r else
                f"{r['study']} " + (r["method"].split(")", 1)[-1].lstrip(", ") or "default"))
        if r["converged"]:
            parts.append(f"{what}: converged in {r['outer']} outer iterations")
        else:
            ext = _opt(r.get("extrapolated_outer"), ".0f")
            parts.append(f"{what}: ||g||/||g_0|| = {r['grad_reduction']:.1e} after "
                         f"{r['outer']} outer iterations (extrapolated total {ext})")
    return "; ".join(parts)


def verdict(rows: list[dict], target: float = 1.6) -> str:
    """Plain-language 'which method wins where' from the main rows of one size.

    A method counts only if it converged with the same answer (energy gap <= 1e-8, max
    vertex difference <= 1e-6 of the width). Unconverged block methods say how far they got
    and, labelled as such, the extrapolated outer iterations and time; the studies follow.
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
    for r in blocks:
        if r["converged"]:
            text += (f"; {r['method']} converges in {r['outer']} outer iterations against "
                     f"{main[0]['outer']} Newton iterations, {r['speedup']:.2f}x")
        else:
            text += "; " + how_far(r, main[0]["time"])
    summary = study_summary(rows)
    return text + (f". Studies (Gauss-Seidel, neighbour): {summary}" if summary else "")


def _frame_case(n: int, args: argparse.Namespace) -> FrameCase:
    """The frame of about n vertices."""
    plate = PlateCase(cells=max(8, round(np.sqrt(n)) - 1), compression=args.compression,
                      vertices_per_cluster=args.vertices_per_cluster,
                      params=ShellParams(penalty_hessian="low_rank"))
    return FrameCase(plate=plate, increment=args.increment, coarse_levels=2)


def _cap(seconds: float | None) -> float | None:
    """A wall-time cap for JSON (None = no cap)."""
    return seconds if seconds is not None and np.isfinite(seconds) else None


def _write(comm: Any, args: argparse.Namespace, n: int, rows: list[dict],
           load: list[tuple[float, float, float]]) -> None:
    """Print the table and verdict; write decomposition_<n>.json (rank 0).

    ``load`` is the 1/5/15-minute load average at the start and end of this size's runs.
    """
    if comm.rank != 0:
        return
    text = verdict(rows)
    frame = FRAME.format(c=args.compression, i=args.increment)
    print(frame)
    print(_table(rows))
    print("verdict: " + text)
    print(f"load average (1/5/15 min) at start {load[0]}, at end {load[1]}")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    out = args.out_dir / f"decomposition_{n}.json"
    study_cap = args.study_seconds if args.study_seconds is not None else args.block_seconds
    out.write_text(json.dumps({"ranks": comm.size, "sizes": [n], "frame": frame,
                               "verdict": text, "block_seconds": _cap(args.block_seconds),
                               "study_seconds": _cap(study_cap),
                               "extrapolation": EXTRAPOLATION_NOTE, "load_average": load,
                               "rows": rows}, indent=1))
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
        load = [os.getloadavg()]
        frame = Frame(comm, fc)
        rows = _main_rows(frame, args)
        if k == 0 and "patches" in args.studies:
            rows += _patch_study(frame, args)
        if k == 0 and "options" in args.studies:
            rows += _options_study(frame, args)
        if k == 0 and "stiffness" in args.studies:
            rows += _stiffness_study(comm, fc, args)
        _write(comm, args, (fc.plate.cells + 1) ** 2, rows, load + [os.getloadavg()])


if __name__ == "__main__":
    main()
