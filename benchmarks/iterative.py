"""Newton iteration time and count: direct vs multigrid CG vs modified Newton (issue 7 item 5).

The scene: a flat unit plate built by linear subdivision of a 25 x 25 grid plate (``L`` levels:
10k = L 2 (10 201 vertices), 40k = L 3 (40 401), 160k = L 4 (160 801), 640k = L 5), held by the
low-rank cluster penalty (``n / 75`` Gaussian clusters, ``benchmarks.shell_solve.cluster_matrix``)
to its own shape compressed by 7 % along x, started from a 1e-4 random out-of-plane
perturbation: it wrinkles. Stiffnesses k_L 1e3, k_B 1e-1, k_P 1e3 (the author's defaults).

Methods (``--methods``), each a fresh :class:`~solvers.shell_newton.ShellNewtonSolver` from the
same start with the same Hessian mode (``--hessian``, default the PSD "gauss_newton"):

* ``direct``: augmented LDL^T (MUMPS) of ``[[A, G^T], [G, -I]]``, analysis reused;
* ``multigrid``: CG + PCMG on the subdivision hierarchy, true residual 1e-8 (fixed forcing);
* ``multigrid-ew``: the same with the Eisenstat-Walker forcing term (inexact Newton);
* ``modified``: direct, one factorisation reused up to 4 iterations (refresh ratio 0.5).

Each runs ``--iterations`` Newton iterations (or stops at ``--rtol``) and reports the time per
Newton iteration (evaluation + linear solve + line search), the split, CG iterations, the
gradient-norm history and its largest relative deviation from the direct run's ("same Newton
convergence"), and the process peak RSS growth. Target (issue 7): a Newton iteration at 160k
under 2 s with the same convergence as the direct solve.

Usage::

    python benchmarks/iterative.py --quick                    # 10k (while developing)
    python benchmarks/iterative.py --sizes 10k 40k 160k       # the issue's sizes

Prints a table and writes benchmarks/results/iterative.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.shell_solve import cluster_matrix, proc_status_mib, reset_peak_rss  # noqa: E402
from meshes.shells import grid_plate  # noqa: E402
from models.backend import PETSc  # noqa: E402
from models.shell.energy import ShellEnergy, ShellParams  # noqa: E402
from models.shell.rest import RestState  # noqa: E402
from models.shell.topology import ShellTopology  # noqa: E402
from solvers.multigrid import MultigridOptions, ShellHierarchy  # noqa: E402
from solvers.shell_newton import (  # noqa: E402
    ModifiedNewtonOptions,
    ShellNewtonOptions,
    ShellNewtonSolver,
    ShellSolveError,
    ShellSolveReport,
)

LEVELS: dict[str, int] = {"10k": 2, "40k": 3, "160k": 4, "640k": 5, "2.5M": 6}
COARSE_CELLS = 25
COMPRESSION = 0.07
RESULTS = Path(__file__).resolve().parent / "results" / "iterative.json"
METHODS: dict[str, dict] = {
    "direct": {},
    "multigrid": {"linear_method": "multigrid"},
    "multigrid-ew": {"linear_method": "multigrid",
                     "multigrid": MultigridOptions(forcing="eisenstat_walker")},
    "modified": {"modified": ModifiedNewtonOptions(enabled=True)},
}


@dataclass
class Scene:
    """The compressed plate of one size: hierarchy, energy, start."""

    hierarchy: ShellHierarchy
    energy: ShellEnergy
    x0: np.ndarray
    setup_time: float


def build_scene(size: str, compression: float = COMPRESSION) -> Scene:
    """The wrinkling plate of ``size`` (see the module docstring)."""
    t0 = time.perf_counter()
    hier = ShellHierarchy.build(*grid_plate(COARSE_CELLS, COARSE_CELLS), levels=LEVELS[size])
    pts, faces = hier.vertices, hier.faces
    topo = ShellTopology.from_faces(faces, len(pts))
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, penalty_hessian="low_rank")
    energy = ShellEnergy(topo, RestState.from_positions(topo, pts), params,
                         H=cluster_matrix(pts, 75))
    energy.set_target(compressed(pts, compression))
    x0 = compressed(pts, compression)
    x0[:, 2] += 1e-4 * np.random.default_rng(1).standard_normal(len(pts))
    return Scene(hier, energy, x0, time.perf_counter() - t0)


def compressed(pts: np.ndarray, compression: float) -> np.ndarray:
    """The plate scaled by ``1 - compression`` along x about x = 0.5."""
    y = pts.copy()
    y[:, 0] = 0.5 + (1.0 - compression) * (pts[:, 0] - 0.5)
    return y


def run_method(scene: Scene, method: str, args: argparse.Namespace) -> dict:
    """One Newton solve with ``method``; the row of the table."""
    opts = ShellNewtonOptions(rtol=args.rtol, max_iterations=args.iterations,
                              hessian=args.hessian, **METHODS[method])
    rss0 = proc_status_mib("VmRSS")
    reset_peak_rss()
    cpu0 = time.process_time()
    solver = ShellNewtonSolver(scene.energy, opts,  # type: ignore[arg-type]
                               hierarchy=scene.hierarchy)
    try:
        _, report = solver.minimize(scene.x0)
        reason = report.reason
    except ShellSolveError as err:
        report, reason = err.report, f"failed: {err.report.reason}"
    row = row_of(method, report, reason, proc_status_mib("VmHWM") - rss0)
    row["cpu_iteration"] = (time.process_time() - cpu0) / max(report.iterations, 1)
    return row


def row_of(method: str, r: ShellSolveReport, reason: str, peak_mib: float) -> dict:
    """Table row of one run."""
    its = max(r.iterations, 1)
    return {"method": method, "reason": reason, "iterations": r.iterations,
            "t_iteration": r.time_total / its, "t_eval": r.time_evaluate / its,
            "t_factorize": r.time_factorize / its, "t_solve": r.time_solve / its,
            "t_line_search": r.time_line_search / its, "t_total": r.time_total,
            "factorizations": r.factorizations, "cg_iterations": r.krylov_iterations,
            "cg_fallbacks": r.krylov_fallbacks, "reused": r.reused_iterations,
            "grad_norms": r.grad_norms.tolist(), "energy": r.energy, "peak_mib": peak_mib}


def deviation(rows: list[dict]) -> None:
    """Add ``dev``: max_k |g_k - g_k(direct)| / g_k(direct) over the common iterations."""
    ref = next((r for r in rows if r["method"] == "direct"), None)
    for r in rows:
        if ref is None:
            r["dev"] = None
            continue
        k = min(len(ref["grad_norms"]), len(r["grad_norms"]))
        a, b = np.array(r["grad_norms"][:k]), np.array(ref["grad_norms"][:k])
        r["dev"] = float(np.max(np.abs(a - b) / b))


HEADER = (f"{'size':>5} {'n':>7} {'method':>13} {'its':>4} {'t/it':>7} {'cpu/it':>7} {'eval':>6} "
          f"{'fact':>6} {'solve':>6} {'ls':>6} {'fact#':>5} {'cg':>5} {'fb':>3} {'dev':>8} "
          f"{'peakMiB':>8} {'|g| final':>10}")


def print_row(size: str, n: int, r: dict) -> None:
    """One line of the table."""
    dev = "-" if r["dev"] is None else f"{r['dev']:.1e}"
    print(f"{size:>5} {n:>7} {r['method']:>13} {r['iterations']:>4} {r['t_iteration']:7.3f} "
          f"{r['cpu_iteration']:7.3f} "
          f"{r['t_eval']:6.3f} {r['t_factorize']:6.3f} {r['t_solve']:6.3f} "
          f"{r['t_line_search']:6.3f} {r['factorizations']:>5} {r['cg_iterations']:>5} "
          f"{r['cg_fallbacks']:>3} {dev:>8} {r['peak_mib']:8.0f} {r['grad_norms'][-1]:10.3e}",
          flush=True)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", default=["10k", "40k", "160k"], choices=list(LEVELS))
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    p.add_argument("--hessian", default="gauss_newton",
                   choices=["gauss_newton", "projected", "exact"])
    p.add_argument("--iterations", type=int, default=8, help="Newton iterations per run")
    p.add_argument("--rtol", type=float, default=1e-12, help="stop earlier at this rtol")
    p.add_argument("--quick", action="store_true", help="10k only")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.quick:
        args.sizes = ["10k"]
    return args


def main(argv: list[str] | None = None) -> None:
    """Run every (size, method), print the table, write the JSON."""
    args = parse_args(argv)
    PETSc.Sys.pushErrorHandler("python")
    print(HEADER)
    out: list[dict] = []
    for size in args.sizes:
        scene = build_scene(size)
        n = scene.energy.n_vertices
        rows = [run_method(scene, m, args) for m in args.methods]
        deviation(rows)
        for r in rows:
            r.update(size=size, n=n, setup_time=scene.setup_time)
            print_row(size, n, r)
        out += rows
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"python": platform.python_version(), "petsc": PETSc.Sys.getVersion(),
            "cpus": os.cpu_count(), "omp_threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average_end": os.getloadavg(), "hessian": args.hessian,
            "iterations": args.iterations, "rtol": args.rtol,
            "units": "seconds per Newton iteration (t_* wall, cpu_iteration = process CPU "
                     "time, the better figure on a shared machine), peak_mib = VmHWM growth during "
                     "the run; dev = max relative deviation of ||g_k|| from the direct run"}
    args.out.write_text(json.dumps({"meta": meta, "rows": out}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
