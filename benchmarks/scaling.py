"""Per-frame time and peak memory of the shell solve from 10k vertices up (issue 7 item 6).

The scene of :mod:`benchmarks.iterative` (a 25 x 25 grid plate subdivided ``L`` times, held by
the low-rank cluster penalty to its 7 %-compressed self, wrinkling) at 10k (L 2), 40k (L 3),
160k (L 4), 640k (L 5) and 2.5M (L 6) vertices. Two frames per size:

* frame 0: from the flat, perturbed start at 7 % compression;
* frame 1: the target compressed to 7.5 %, warm-started from frame 0 (a typical frame).

Each frame is a shell Newton solve with the PSD Gauss-Newton Hessian to ``||g|| <= rtol g_0``
(``g_0`` the initial gradient norm of frame 0), at most ``--iterations`` Newton iterations.
The Gauss-Newton iteration count of a wrinkling frame varies erratically with the size (measured
at 10k / 40k with rtol 1e-3: frame 1 took 30 (cap) / 2 iterations), which would swamp the
growth fit; by default a frame is therefore a fixed ``--iterations 5`` Newton iterations
(``--rtol 1e-14``, never reached), i.e. the fit measures the cost of a frame's work, and
the frame's iteration count is reported. The linear solve is that of ``--method`` (default
"multigrid-ew": CG + geometric multigrid on the subdivision hierarchy, Eisenstat-Walker
forcing; "direct" is the augmented MUMPS LDL^T).
Every size runs in its own process, so the peak RSS (VmHWM) is that size's alone (set-up
included). The growth exponents ``t_frame ~ n^p`` and ``peak ~ n^q`` are fitted with
``np.polyfit`` on log-log over the sizes run and printed.

Usage::

    python benchmarks/scaling.py --quick                              # 10k, 40k
    python benchmarks/scaling.py --sizes 10k 40k 160k 640k 2.5M       # quiet machine

Prints a table and writes benchmarks/results/scaling.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.iterative import LEVELS, METHODS, build_scene, compressed  # noqa: E402
from benchmarks.shell_solve import proc_status_mib  # noqa: E402
from solvers.shell_newton import (  # noqa: E402
    ShellNewtonOptions,
    ShellNewtonSolver,
    ShellSolveError,
    ShellSolveReport,
)

RESULTS = Path(__file__).resolve().parent / "results" / "scaling.json"
FRAME_COMPRESSION = (0.07, 0.075)


def solve_frame(solver: ShellNewtonSolver, x: np.ndarray) -> tuple[np.ndarray, dict]:
    """One frame: (x, row with wall / CPU time, iterations, CG iterations, |g|)."""
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        x, report = solver.minimize(x)
        reason = report.reason
    except ShellSolveError as err:
        x, report, reason = err.x, err.report, f"failed: {err.report.reason}"
    return x, frame_row(report, reason, time.perf_counter() - wall, time.process_time() - cpu)


def frame_row(r: ShellSolveReport, reason: str, wall: float, cpu: float) -> dict:
    """The measured figures of one frame."""
    return {"wall": wall, "cpu": cpu, "reason": reason, "iterations": r.iterations,
            "cg_iterations": r.krylov_iterations, "cg_fallbacks": r.krylov_fallbacks,
            "factorizations": r.factorizations, "t_eval": r.time_evaluate,
            "t_linear": r.time_factorize + r.time_solve, "grad_norm": r.grad_norm,
            "energy": r.energy}


def run_one(size: str, method: str, iterations: int, rtol: float) -> dict:
    """Both frames of one size in this process; the JSON row."""
    scene = build_scene(size)
    energy = scene.energy
    g0 = float(np.linalg.norm(energy.evaluate(scene.x0, order=1).grad))  # type: ignore[arg-type]
    opts = ShellNewtonOptions(rtol=rtol, gradient_scale=g0, max_iterations=iterations,
                              hessian="gauss_newton", **METHODS[method])
    solver = ShellNewtonSolver(energy, opts, hierarchy=scene.hierarchy)  # type: ignore[arg-type]
    x, frames = scene.x0, []
    for c in FRAME_COMPRESSION:
        energy.set_target(compressed(scene.hierarchy.vertices, c))
        x, row = solve_frame(solver, x)
        frames.append(row)
    return {"size": size, "n": energy.n_vertices, "method": method,
            "setup_time": scene.setup_time, "peak_mib": proc_status_mib("VmHWM"),
            "frames": frames}


def run_in_subprocess(size: str, args: argparse.Namespace) -> dict | None:
    """``run_one`` in a fresh interpreter (its own peak RSS); None if it failed."""
    cmd = [sys.executable, __file__, "--one", size, "--method", args.method,
           "--iterations", str(args.iterations), "--rtol", str(args.rtol)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        print(f"{size}: failed (exit {proc.returncode}): {proc.stderr.strip()[-400:]}")
        return None
    return json.loads(lines[-1])


HEADER = (f"{'size':>5} {'n':>8} {'setup':>7} {'f0 wall':>8} {'f0 cpu':>7} {'f0 its':>6} "
          f"{'f1 wall':>8} {'f1 cpu':>7} {'f1 its':>6} {'f1 cg':>6} {'peakMiB':>8} f1 reason")


def print_row(r: dict) -> None:
    """One line of the table."""
    f0, f1 = r["frames"]
    print(f"{r['size']:>5} {r['n']:>8} {r['setup_time']:7.2f} {f0['wall']:8.2f} "
          f"{f0['cpu']:7.2f} {f0['iterations']:>6} {f1['wall']:8.2f} {f1['cpu']:7.2f} "
          f"{f1['iterations']:>6} {f1['cg_iterations']:>6} {r['peak_mib']:8.0f} "
          f"{f1['reason']}", flush=True)


def exponents(rows: list[dict]) -> dict[str, float] | None:
    """Fitted ``p`` of ``y ~ n^p`` (np.polyfit on log-log) for frame time, CPU and memory."""
    if len(rows) < 2:
        return None
    n = np.log([r["n"] for r in rows])
    fits = {"frame1_wall": [r["frames"][1]["wall"] for r in rows],
            "frame1_cpu": [r["frames"][1]["cpu"] for r in rows],
            "frame1_cpu_per_newton_iteration": [
                r["frames"][1]["cpu"] / max(r["frames"][1]["iterations"], 1) for r in rows],
            "peak_mib": [r["peak_mib"] for r in rows]}
    return {k: float(np.polyfit(n, np.log(v), 1)[0]) for k, v in fits.items()}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", default=["10k", "40k", "160k", "640k"],
                   choices=list(LEVELS))
    p.add_argument("--method", default="multigrid-ew", choices=list(METHODS))
    p.add_argument("--iterations", type=int, default=5, help="Newton iterations per frame")
    p.add_argument("--rtol", type=float, default=1e-14,
                   help="frame tolerance relative to g_0 (default: never reached)")
    p.add_argument("--quick", action="store_true", help="10k and 40k only")
    p.add_argument("--one", default="", help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.quick:
        args.sizes = ["10k", "40k"]
    return args


def main(argv: list[str] | None = None) -> None:
    """Run every size in its own process, print the table and exponents, write the JSON."""
    args = parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one, args.method, args.iterations, args.rtol)))
        return
    print(HEADER)
    rows = []
    for size in args.sizes:
        row = run_in_subprocess(size, args)
        if row is not None:
            print_row(row)
            rows.append(row)
    fit = exponents(rows)
    if fit is not None:
        print("growth exponents p (y ~ n^p): " + ", ".join(f"{k} {v:.3f}" for k, v in fit.items()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"python": platform.python_version(), "cpus": os.cpu_count(),
            "omp_threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average_end": os.getloadavg(), "method": args.method,
            "iterations": args.iterations, "rtol": args.rtol,
            "units": "seconds (wall and process CPU per frame), peak_mib = VmHWM of the size's "
                     "process (set-up included)", "exponents": fit}
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
