"""Per-frame time and peak memory of the shell solve from 10k vertices up (issue 7 item 6).

The scene of :mod:`benchmarks.iterative`: a ``C x C`` grid plate (``--base-cells``, default
25) subdivided ``L`` times, i.e. ``n = (2^L C + 1)^2`` vertices (C = 25: 10k = L 2, 40k = L 3,
160k = L 4, 640k = L 5, 2.5M = L 6; C = 35, L 5 gives 1.26M), held by the low-rank cluster
penalty (``n / 75`` Gaussian clusters, :func:`benchmarks.shell_solve.cluster_matrix`) to its
7 %-compressed self, wrinkling. Two frames per size:

* frame 0: from the flat, perturbed start at 7 % compression (it also pays the first
  multigrid set-up: symbolic Galerkin products, KSP creation);
* frame 1: the target compressed to 7.5 %, warm-started from frame 0 (a typical frame; the
  growth fit uses this one).

Each frame is a shell Newton solve with the PSD Gauss-Newton Hessian to ``||g|| <= rtol g_0``
(``g_0`` the initial gradient norm of frame 0), at most ``--iterations`` Newton iterations.
The Gauss-Newton iteration count of a wrinkling frame varies erratically with the size (measured
at 10k / 40k with rtol 1e-3: frame 1 took 30 (cap) / 2 iterations), which would swamp the
growth fit; by default a frame is therefore a fixed ``--iterations 5`` Newton iterations
(``--rtol 1e-14``, never reached), i.e. the fit measures the cost of a frame's work, and
the frame's Newton and CG iteration counts are reported. The linear solve is that of
``--method`` (default "multigrid-ew": CG + geometric multigrid on the subdivision hierarchy,
Eisenstat-Walker forcing; "direct" is the augmented MUMPS LDL^T).

Every size runs in its own process, so its peak RSS (VmHWM) is that size's alone. The set-up
(subdivision hierarchy, topology and rest state, clusters, energy, solver) is timed stage by
stage, wall and process CPU, and is not part of a frame. CPU time is the fairer figure on a
shared machine; the load average is recorded at the start and end of every size.

Growth exponents ``y ~ n^p`` are least-squares lines on log-log (``np.polyfit``) over the sizes
of one method, with the fit's residual (RMS and largest ``|log y - (p log n + c)|``) and the
local slopes between consecutive sizes, for: frame wall and CPU time, CPU per Newton
iteration, CG iterations per Newton iteration, set-up CPU (total, hierarchy, clusters) and
peak RSS.

Measured 2026-11-22 (session 3, 2 cores shared by five engineers, load 1.2-7; JSON in
benchmarks/results/scaling.json): multigrid-ew frame 1 CPU 0.64 / 2.05 / 11.0 / 62.0 / 129 s
at 10k / 40k / 160k / 640k / 1.26M (L5x35), 28-53 CG iterations per 5-iteration frame, peak
RSS 0.36 / 0.62 / 1.7 / 5.8 / 11.3 GiB; fitted CPU exponent 1.13 (local slope 1.09 at the
top), memory local slope 0.97. 2.5M (L6) would need ~23 GiB (x4 of 640k) and was not run.

``--clusters-study`` times instead, per size, the application's cluster construction
(:func:`models.embedding.clusters.build_clusters` stage by stage at the same ``n / 75``
clusters) against the benchmark's KD-tree weights, and fits each stage's CPU exponent.

Usage::

    python benchmarks/scaling.py --quick                              # 10k, 40k
    python benchmarks/scaling.py --sizes 10k 40k 160k 640k            # ~1 h on a shared machine
    python benchmarks/scaling.py --sizes 640k --base-cells 35 --append   # add 1.26M vertices
    python benchmarks/scaling.py --method direct --out benchmarks/results/scaling_direct.json
    python benchmarks/scaling.py --clusters-study --sizes 10k 40k 160k

Prints a table and writes benchmarks/results/scaling.json (rewritten after every size).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from benchmarks.cluster_setup import build_stages
from benchmarks.iterative import (
    COARSE_CELLS,
    COMPRESSION,
    LEVELS,
    METHODS,
    Scene,
    compressed,
)
from benchmarks.shell_solve import cluster_matrix, proc_status_mib
from benchmarks.timing import Timings, power_fit, stopwatch
from meshes.shells import grid_plate
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState
from models.shell.topology import ShellTopology
from solvers.multigrid import ShellHierarchy
from solvers.shell_newton import (
    ShellNewtonOptions,
    ShellNewtonSolver,
    ShellSolveError,
    ShellSolveReport,
)

RESULTS = Path(__file__).resolve().parent / "results" / "scaling.json"
CLUSTER_RESULTS = RESULTS.with_name("setup_clusters.json")
FRAME_COMPRESSION = (0.07, 0.075)
SIZES: dict[str, int] = {"2.5k": 1, **LEVELS}
CLUSTER_RATIO = 75  # vertices per cluster (as benchmarks.iterative)
def size_label(levels: int, cells: int) -> str:
    """``"640k"`` for the default base grid, else ``"L<levels>x<cells>"``."""
    if cells == COARSE_CELLS:
        return next(k for k, v in SIZES.items() if v == levels)
    return f"L{levels}x{cells}"


def plate_vertices(levels: int, cells: int) -> int:
    """Vertices of a ``cells x cells`` grid plate after ``levels`` subdivisions."""
    return (2**levels * cells + 1) ** 2


def build_timed_scene(levels: int, cells: int) -> tuple[Scene, Timings, int]:
    """The wrinkling plate (as :func:`benchmarks.iterative.build_scene`), set-up timed by stage.

    Returns ``(scene, timings, cluster count)``.
    """
    t: Timings = {}
    with stopwatch(t, "hierarchy"):
        hier = ShellHierarchy.build(*grid_plate(cells, cells), levels=levels)
    pts = hier.vertices
    with stopwatch(t, "topology_rest"):
        topo = ShellTopology.from_faces(hier.faces, len(pts))
        rest = RestState.from_positions(topo, pts)
    with stopwatch(t, "clusters"):
        h = cluster_matrix(pts, CLUSTER_RATIO)
    with stopwatch(t, "energy"):
        params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, penalty_hessian="low_rank")
        energy = ShellEnergy(topo, rest, params, H=h)
        energy.set_target(compressed(pts, COMPRESSION))
    x0 = compressed(pts, COMPRESSION)
    x0[:, 2] += 1e-4 * np.random.default_rng(1).standard_normal(len(pts))
    return Scene(hier, energy, x0, sum(v["wall"] for v in t.values())), t, h.shape[0]


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
    """The measured figures of one frame (``t_*``: wall seconds inside the solve)."""
    return {"wall": wall, "cpu": cpu, "reason": reason, "iterations": r.iterations,
            "cg_iterations": r.krylov_iterations, "cg_fallbacks": r.krylov_fallbacks,
            "factorizations": r.factorizations, "t_eval": r.time_evaluate,
            "t_line_search": r.time_line_search, "t_setup_or_factorize": r.time_factorize,
            "t_analysis": r.time_analysis, "t_solve": r.time_solve,
            "t_linear": r.time_factorize + r.time_solve, "grad_norm": r.grad_norm,
            "energy": r.energy}


def run_one(levels: int, cells: int, method: str, iterations: int, rtol: float) -> dict:
    """Set-up and both frames of one size in this process; the JSON row."""
    load_start = os.getloadavg()
    scene, setup, clusters = build_timed_scene(levels, cells)
    energy = scene.energy
    with stopwatch(setup, "solver"):
        g0 = float(np.linalg.norm(energy.evaluate(scene.x0, order=1).grad))  # type: ignore[arg-type]
        opts = ShellNewtonOptions(rtol=rtol, gradient_scale=g0, max_iterations=iterations,
                                  hessian="gauss_newton", **METHODS[method])
        solver = ShellNewtonSolver(energy, opts, hierarchy=scene.hierarchy)  # type: ignore[arg-type]
    setup_peak = proc_status_mib("VmHWM")
    x, frames = scene.x0, []
    for c in FRAME_COMPRESSION:
        energy.set_target(compressed(scene.hierarchy.vertices, c))
        x, row = solve_frame(solver, x)
        frames.append(row)
    return {"size": size_label(levels, cells), "levels": levels, "base_cells": cells,
            "n": energy.n_vertices, "clusters": clusters, "method": method, "setup": setup,
            "setup_time": sum(v["wall"] for v in setup.values()),
            "setup_cpu": sum(v["cpu"] for v in setup.values()), "setup_peak_mib": setup_peak,
            "peak_mib": proc_status_mib("VmHWM"), "load_start": load_start,
            "load_end": os.getloadavg(), "frames": frames}


def run_in_subprocess(levels: int, args: argparse.Namespace) -> dict | None:
    """``run_one`` in a fresh interpreter (its own peak RSS); None if it failed."""
    cmd = [sys.executable, __file__, "--one", str(levels), "--base-cells", str(args.base_cells),
           "--iterations", str(args.iterations), "--rtol", str(args.rtol)]
    cmd += ["--clusters-study"] if args.clusters_study else ["--method", args.method]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        print(f"L{levels}x{args.base_cells}: failed (exit {proc.returncode}): "
              f"{proc.stderr.strip()[-400:]}", flush=True)
        return None
    return json.loads(lines[-1])


def cluster_study(levels: int, cells: int) -> dict:
    """Time the application's cluster construction by stage at ``n / 75`` clusters.

    The stages of :func:`models.embedding.clusters.build_clusters` (edge graph, farthest-point
    centres, Gaussian weights by truncated Dijkstra, nearest-centre partition, smallest singular
    value of H), against the benchmark's KD-tree weights :func:`cluster_matrix`.
    """
    hier = ShellHierarchy.build(*grid_plate(cells, cells), levels=levels)
    v, t = hier.vertices, Timings()
    built = build_stages(v, hier.faces, t)
    with stopwatch(t, "kdtree_cluster_matrix"):
        cluster_matrix(v, CLUSTER_RATIO)
    return {"size": size_label(levels, cells), "n": len(v), "clusters": int(built.centres.size),
            "method": "clusters", "setup": t, "peak_mib": proc_status_mib("VmHWM")}


# --- growth fits ------------------------------------------------------------------------------

QUANTITIES: dict[str, Callable[[dict], float]] = {
    "frame1_wall": lambda r: r["frames"][1]["wall"],
    "frame1_cpu": lambda r: r["frames"][1]["cpu"],
    "frame1_cpu_per_newton_iteration":
        lambda r: r["frames"][1]["cpu"] / max(r["frames"][1]["iterations"], 1),
    "frame1_cg_per_newton_iteration":
        lambda r: r["frames"][1]["cg_iterations"] / max(r["frames"][1]["iterations"], 1),
    "setup_cpu": lambda r: r["setup_cpu"],
    "setup_hierarchy_cpu": lambda r: r["setup"]["hierarchy"]["cpu"],
    "setup_clusters_cpu": lambda r: r["setup"]["clusters"]["cpu"],
    "setup_energy_cpu": lambda r: r["setup"]["energy"]["cpu"],
    "peak_mib": lambda r: r["peak_mib"],
}


def exponents(rows: list[dict]) -> dict[str, dict] | None:
    """Fits of :data:`QUANTITIES` (cluster study: every stage's CPU) over ``rows``, sorted by
    n; None for fewer than 2 sizes."""
    rows = sorted(rows, key=lambda r: r["n"])
    if len(rows) < 2:
        return None
    n = np.array([r["n"] for r in rows], dtype=float)
    getters = QUANTITIES if rows[0]["method"] != "clusters" else {
        f"{k}_cpu": (lambda r, k=k: r["setup"][k]["cpu"]) for k in rows[0]["setup"]}
    out: dict[str, dict] = {}
    for name, get in getters.items():
        y = np.array([get(r) for r in rows], dtype=float)
        if np.all(y > 0):
            out[name] = power_fit(n, y)
    return out


# --- table, JSON ------------------------------------------------------------------------------

HEADER = (f"{'size':>7} {'n':>8} {'set-up':>7} {'(cpu)':>7} {'f0 wall':>8} {'(cpu)':>7} "
          f"{'f1 wall':>8} {'(cpu)':>7} {'its':>3} {'cg':>4} {'peakMiB':>8} {'load':>5} "
          "f1 reason")


def print_row(r: dict) -> None:
    """One line of the table (set-up and frames: wall seconds, process CPU in brackets)."""
    if r["method"] == "clusters":
        stages = " ".join(f"{k} {v['cpu']:.2f}" for k, v in r["setup"].items())
        print(f"{r['size']:>7} {r['n']:>8} clusters {r['clusters']}, CPU s: {stages}; "
              f"peak {r['peak_mib']:.0f} MiB", flush=True)
        return
    f0, f1 = r["frames"]
    print(f"{r['size']:>7} {r['n']:>8} {r['setup_time']:7.1f} {r['setup_cpu']:7.1f} "
          f"{f0['wall']:8.2f} {f0['cpu']:7.2f} {f1['wall']:8.2f} {f1['cpu']:7.2f} "
          f"{f1['iterations']:>3} {f1['cg_iterations']:>4} {r['peak_mib']:8.0f} "
          f"{r['load_end'][0]:5.2f} {f1['reason']}", flush=True)


def print_fits(fit: dict[str, dict]) -> None:
    """The fitted exponents with residuals and local slopes."""
    print("growth exponents p (y ~ n^p), rms / max log residual, local slopes:")
    for k, v in fit.items():
        local = " ".join(f"{s:.3f}" for s in v["local"])
        print(f"  {k:>34}: p = {v['p']:.3f}  res {v['rms_log_residual']:.3f} / "
              f"{v['max_log_residual']:.3f}  local [{local}]")


def merge(old: list[dict], new: list[dict]) -> list[dict]:
    """``old`` rows not replaced by a ``new`` row of the same (size, method), plus ``new``."""
    keys = {(r["size"], r["method"]) for r in new}
    kept = [r for r in old if (r["size"], r["method"]) not in keys]
    return sorted(kept + new, key=lambda r: r["n"])


def save(args: argparse.Namespace, rows: list[dict]) -> dict[str, dict] | None:
    """Write the JSON (rows of this method, exponents, provenance); return the fits."""
    fit = exponents(rows)
    meta = {"python": platform.python_version(), "cpus": os.cpu_count(),
            "omp_threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average_end": os.getloadavg(), "method": args.method,
            "iterations": args.iterations, "rtol": args.rtol,
            "frame_compression": FRAME_COMPRESSION, "cluster_ratio": CLUSTER_RATIO,
            "units": "seconds (wall and process CPU) per frame and per set-up stage; "
                     "peak_mib = VmHWM of the size's process, setup_peak_mib after the set-up; "
                     "exponents fitted over the frame 1 rows by np.polyfit on log-log",
            "exponents": fit}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    return fit


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", default=["10k", "40k", "160k", "640k"],
                   choices=list(SIZES), help="subdivision level by name (of the 25 x 25 plate)")
    p.add_argument("--base-cells", type=int, default=COARSE_CELLS,
                   help="cells per side of the coarse grid plate (n = (2^L C + 1)^2)")
    p.add_argument("--method", default="multigrid-ew", choices=list(METHODS))
    p.add_argument("--iterations", type=int, default=5, help="Newton iterations per frame")
    p.add_argument("--rtol", type=float, default=1e-14,
                   help="frame tolerance relative to g_0 (default: never reached)")
    p.add_argument("--quick", action="store_true", help="10k and 40k only")
    p.add_argument("--append", action="store_true",
                   help="merge with the rows already in --out (same size + method replaced)")
    p.add_argument("--clusters-study", action="store_true",
                   help="time the application's cluster construction (models.embedding."
                   "clusters) by stage instead of the frames; default --out "
                   "benchmarks/results/setup_clusters.json")
    p.add_argument("--refit", action="store_true",
                   help="run nothing: refit the rows already in --out and rewrite it")
    p.add_argument("--one", type=int, default=-1, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.out is None:
        args.out = CLUSTER_RESULTS if args.clusters_study else RESULTS
    if args.clusters_study:
        args.method = "clusters"
    if args.base_cells < 1:
        p.error("--base-cells: expected an integer >= 1")
    if args.quick:
        args.sizes = ["10k", "40k"]
    if args.refit:
        args.append, args.sizes = True, []
    return args


def previous_rows(args: argparse.Namespace) -> list[dict]:
    """Rows of ``--method`` already in ``--out`` (``--append``), else none; ``--refit`` takes
    the method, iterations and rtol from the file's meta."""
    if not (args.append and args.out.is_file()):
        return []
    doc = json.loads(args.out.read_text())
    if args.refit:  # keep the settings the rows were run with
        meta = doc["meta"]
        args.method, args.iterations, args.rtol = meta["method"], meta["iterations"], meta["rtol"]
    return [r for r in doc["rows"] if r["method"] == args.method]


def main(argv: list[str] | None = None) -> None:
    """Run every size in its own process, print the table and exponents, write the JSON."""
    args = parse_args(argv)
    if args.one >= 0:
        row = (cluster_study(args.one, args.base_cells) if args.clusters_study else
               run_one(args.one, args.base_cells, args.method, args.iterations, args.rtol))
        print(json.dumps(row))
        return
    if not args.clusters_study:
        print("set-up and frames: wall s, process CPU s in brackets; load = 1-min load average "
              "at the end of the size")
        print(HEADER)
    old, new = previous_rows(args), list[dict]()
    for r in old:
        print_row(r)
    for size in args.sizes:
        print(f"# {size_label(SIZES[size], args.base_cells)}: "
              f"{plate_vertices(SIZES[size], args.base_cells)} vertices, started "
              f"{time.strftime('%H:%M:%S', time.gmtime())} UTC", flush=True)
        result = run_in_subprocess(SIZES[size], args)
        if result is not None:
            print_row(result)
            new.append(result)
            save(args, merge(old, new))
    fit = save(args, merge(old, new))
    if fit is not None:
        print_fits(fit)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
