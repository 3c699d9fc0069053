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
* ``modified``: direct, one factorisation reused up to 4 iterations (refresh ratio 0.5);
* ``multigrid-fast``: :data:`FAST` (CG to a fixed true residual 1e-4, Chebyshev bounds once
  per Newton solve, SBAIJ level products, shifted CG instead of a direct fallback);
* ``multigrid-fast-ew``: the same with the Eisenstat-Walker forcing term;
* ``multigrid-fast-tight``: :data:`FAST` with CG to the true residual 1e-8 every iteration
  (the direct solve's Newton history to the CG tolerance);
* ``multigrid-fast-w``, ``multigrid-fast-ew-w``: the same two with W-cycles;
* ``multigrid-phase``, ``multigrid-phase-ew``, ``multigrid-phase-tight``: ``multigrid-fast``,
  ``-fast-ew`` and ``-fast-tight`` with the wrinkle-phase coarse space
  (:mod:`solvers.phase_space`, ``MultigridOptions.phase_space``); ``multigrid-phase-ew-d1``
  the EW one with one Chebyshev step per level (``-d1-w`` with W-cycles),
  ``multigrid-phase-ew-l1`` with the hats of hierarchy level 1; ``--repeat 2`` reports the
  second of two solves by one solver (its one-time set-up paid by the first).

``--threads T`` runs the element kernels (``ShellParams.threads``) and the multigrid's level and
penalty products (``MultigridOptions.threads``) on T threads; the table then shows wall below
CPU time, and ``--breakdown`` prints both per part.

Each runs ``--iterations`` Newton iterations (or stops at ``--rtol``) and reports the time per
Newton iteration (evaluation + linear solve + line search), the split, CG iterations, the
gradient-norm history and its largest relative deviation from the direct run's ("same Newton
convergence"), and the process peak RSS growth. Target (issue 7): a Newton iteration at 160k
under 2 s with the same convergence as the direct solve.

``--to-tolerance RTOL`` instead solves a warm-started frame to ``||g|| <= RTOL ||g_0||`` with
every method: the plate's minimiser at 7 % compression (:func:`prepared`, grid-sequenced and
cached under :data:`CACHE`) moved with a target compressed ``--increment`` more
(:func:`frame_scene`). The direct solve runs once and is cached there too
(``--fresh-direct`` reruns it). Per method: Newton iterations and the difference to the
direct count, CPU and wall time per iteration and in total, CG iterations, set-ups, the
final energy gap and the largest vertex difference to the direct minimiser, and the largest
accepted true CG residual.

Usage::

    python benchmarks/iterative.py --quick                    # 10k (while developing)
    python benchmarks/iterative.py --sizes 10k 40k 160k       # the issue's sizes
    python benchmarks/iterative.py --sizes 160k --hessian exact --to-tolerance 1e-8
    python benchmarks/iterative.py --sizes 160k --hessian exact --to-tolerance 1e-8 \
        --methods multigrid-phase-ew --repeat 2 --breakdown --threads 2

Prints a table and writes benchmarks/results/iterative.json (``--to-tolerance``:
benchmarks/results/iterative_<sizes>_conv.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import dataclass, replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from benchmarks.shell_solve import cluster_matrix, proc_status_mib, reset_peak_rss
from meshes.shells import grid_plate
from models.backend import PETSc
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.rest import RestState
from models.shell.topology import ShellTopology
from solvers.multigrid import KrylovStats, MultigridOptions, ShellHierarchy
from solvers.shell_newton import (
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
CACHE = (Path(os.environ["WRINKLES_CACHE"]) if os.environ.get("WRINKLES_CACHE")
         else Path(__file__).resolve().parents[1] / ".cache") / "iterative"
"""Prepared minimisers and direct solves: ``$WRINKLES_CACHE/iterative`` or ``.cache/iterative``."""
PREPARE = ShellNewtonOptions(rtol=1e-6, hessian="exact", far_hessian="gauss_newton")
"""Newton options of the grid-sequenced preparation of a frame (:func:`prepared`), up to 40k."""
PREPARE_MG = ShellNewtonOptions(
    rtol=1e-6, hessian="exact", far_hessian="gauss_newton", linear_method="multigrid",
    multigrid=MultigridOptions(rtol=1e-4, fallback=False, eigen_estimate="solve",
                               level_format="sbaij"))
"""The same with multigrid CG (shifted on breakdown) from 160k on (a direct preparation there
costs tens of minutes on the shared machine)."""
FAST = MultigridOptions(rtol=1e-4, fallback=False, eigen_estimate="solve", level_format="sbaij",
                        target_fraction=0.5)
"""The measured fast multigrid: CG to a fixed true residual 1e-4 (raised for the last step to
what half the Newton tolerance needs), Chebyshev bounds once per Newton solve, SBAIJ level
products, shifted CG (no direct fallback) on indefinite matrices."""
METHODS: dict[str, dict] = {
    "direct": {},
    "multigrid": {"linear_method": "multigrid"},
    "multigrid-ew": {"linear_method": "multigrid",
                     "multigrid": MultigridOptions(forcing="eisenstat_walker")},
    "modified": {"modified": ModifiedNewtonOptions(enabled=True)},
    "multigrid-fast": {"linear_method": "multigrid", "multigrid": FAST},
    "multigrid-fast-ew": {"linear_method": "multigrid",
                          "multigrid": replace(FAST, forcing="eisenstat_walker")},
    "multigrid-fast-tight": {"linear_method": "multigrid",
                             "multigrid": replace(FAST, rtol=1e-8, target_fraction=0.0)},
    "multigrid-fast-w": {"linear_method": "multigrid", "multigrid": replace(FAST, cycle="w")},
    "multigrid-fast-ew-w": {"linear_method": "multigrid",
                            "multigrid": replace(FAST, forcing="eisenstat_walker", cycle="w")},
    "multigrid-phase": {"linear_method": "multigrid",
                        "multigrid": replace(FAST, phase_space=True)},
    "multigrid-phase-ew": {"linear_method": "multigrid",
                           "multigrid": replace(FAST, phase_space=True,
                                                forcing="eisenstat_walker")},
    "multigrid-phase-ew-d1": {"linear_method": "multigrid",
                              "multigrid": replace(FAST, phase_space=True, smoother_degree=1,
                                                   forcing="eisenstat_walker")},
    "multigrid-phase-ew-d1-w": {"linear_method": "multigrid",
                                "multigrid": replace(FAST, phase_space=True, smoother_degree=1,
                                                     forcing="eisenstat_walker", cycle="w")},
    "multigrid-phase-ew-l1": {"linear_method": "multigrid",
                              "multigrid": replace(FAST, phase_space=True, phase_level=1,
                                                   forcing="eisenstat_walker")},
    "multigrid-phase-tight": {"linear_method": "multigrid",
                              "multigrid": replace(FAST, phase_space=True, rtol=1e-8,
                                                   target_fraction=0.0)},
}


@dataclass
class Scene:
    """The compressed plate of one size: hierarchy, energy, start."""

    hierarchy: ShellHierarchy
    energy: ShellEnergy
    x0: np.ndarray
    setup_time: float


def build_scene(size: str, compression: float = COMPRESSION, threads: int = 1) -> Scene:
    """The wrinkling plate of ``size`` (see the module docstring)."""
    return scene_at(LEVELS[size], compression, threads)


def scene_at(levels: int, compression: float = COMPRESSION, threads: int = 1) -> Scene:
    """The wrinkling plate subdivided ``levels`` times (``threads``: the energy's kernels)."""
    t0 = time.perf_counter()
    hier = ShellHierarchy.build(*grid_plate(COARSE_CELLS, COARSE_CELLS), levels=levels)
    pts, faces = hier.vertices, hier.faces
    topo = ShellTopology.from_faces(faces, len(pts))
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, penalty_hessian="low_rank",
                         threads=threads)
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


def prepared(levels: int) -> np.ndarray:
    """Minimiser of the plate at ``COMPRESSION`` (``levels`` subdivisions), cached.

    Grid sequencing: the 2-level plate is solved from its noisy flat start, every finer one
    from ``S_{l-1} x_{l-1}`` (the coarser minimiser prolonged by its subdivision matrix), with
    :data:`PREPARE` (direct) up to 40k and :data:`PREPARE_MG` above. Cached under
    :data:`CACHE`.
    """
    path = CACHE / f"prepared_L{levels}_{COARSE_CELLS}_{COMPRESSION}.npz"
    if path.exists():
        return np.load(path)["x"]
    scene = scene_at(levels)
    x0 = scene.x0 if levels <= 2 else \
        scene.hierarchy.subdivision.matrices[-1] @ prepared(levels - 1)
    options = PREPARE if levels <= LEVELS["40k"] else PREPARE_MG
    x, report = ShellNewtonSolver(scene.energy, options,  # type: ignore[arg-type]
                                  hierarchy=scene.hierarchy).minimize(x0)
    print(f"# prepared {len(x)} vertices: {report.summary()}", flush=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, x=x)
    return x


def frame_scene(size: str, increment: float, threads: int = 1) -> Scene:
    """A warm-started frame: the prepared minimiser moved with a target ``increment`` tighter.

    The target is the plate compressed ``COMPRESSION + increment``; the start is the prepared
    minimiser at ``COMPRESSION`` plus the target's displacement (the frame loop's warm start).
    """
    x_prev = prepared(LEVELS[size])
    scene = build_scene(size, threads=threads)
    pts = scene.hierarchy.vertices
    y_old, y_new = compressed(pts, COMPRESSION), compressed(pts, COMPRESSION + increment)
    scene.energy.set_target(y_new)
    return Scene(scene.hierarchy, scene.energy, x_prev + (y_new - y_old), scene.setup_time)


def run_method(scene: Scene, method: str, args: argparse.Namespace) -> dict:
    """One Newton solve with ``method``; the row of the table."""
    return solve_row(scene, method, args)[0]


CPU_PARTS: dict[str, tuple[str, ...]] = {
    "newton": ("_evaluate", "_line_search"),
    "krylov": ("_galerkin_products", "_refresh_products", "_update_coarse", "_create_ksp",
               "_refresh_smoothers", "_update_phase", "_cg", "true_residual", "_fallback"),
}
"""Methods whose process CPU and wall time ``--breakdown`` accumulates: the shell Newton's
evaluations and line search, the multigrid system's set-up parts, CG, true residual, direct
fallback."""


def cpu_timed(obj: object, names: tuple[str, ...], totals: dict[str, dict[str, float]]
              ) -> None:
    """Wrap the bound methods ``names`` of ``obj`` to add their seconds to ``totals``.

    ``totals["cpu"][name]`` gets the process CPU seconds, ``totals["wall"][name]`` the wall
    ones (they differ with ``--threads`` > 1).
    """
    for name in names:
        method = getattr(obj, name)

        def timed(*a: object, _method=method, _name=name, **k: object) -> object:  # noqa: ANN001
            start = {"cpu": time.process_time(), "wall": time.perf_counter()}
            try:
                return _method(*a, **k)
            finally:
                now = {"cpu": time.process_time(), "wall": time.perf_counter()}
                for clock, clock_totals in totals.items():
                    clock_totals[_name] = (clock_totals.get(_name, 0.0) + now[clock]
                                           - start[clock])

        setattr(obj, name, timed)


def solve_row(scene: Scene, method: str, args: argparse.Namespace) -> tuple[dict, np.ndarray]:
    """Newton solves with ``method``: ``(row of the table, final positions)``.

    With ``--repeat N`` the same solver solves the frame N times from the same start and the
    row is the last solve's (the solver's one-time set-up -- symbolic products, SBAIJ copies,
    KSP creation -- paid by the first, as in a frame loop); ``cpu_first`` keeps the first
    solve's CPU seconds.
    """
    opts = ShellNewtonOptions(rtol=args.rtol, max_iterations=args.iterations,
                              hessian=args.hessian, **METHODS[method])
    opts = replace(opts, multigrid=replace(opts.multigrid, threads=args.threads))
    rss0 = proc_status_mib("VmRSS")
    reset_peak_rss()
    cpu0 = time.process_time()
    solver = ShellNewtonSolver(scene.energy, opts,  # type: ignore[arg-type]
                               hierarchy=scene.hierarchy)
    parts: dict[str, dict[str, float]] = {"cpu": {}, "wall": {}}
    if getattr(args, "breakdown", False):
        cpu_timed(solver, CPU_PARTS["newton"], parts)
        if solver.krylov is not None:
            cpu_timed(solver.krylov, CPU_PARTS["krylov"], parts)
    x, report, reason = _minimize(solver, scene.x0)
    cpu_first = time.process_time() - cpu0
    for _ in range(args.repeat - 1):  # the same solver again: the last solve is reported
        for clock_parts in parts.values():
            clock_parts.clear()
        cpu0 = time.process_time()
        if solver.krylov is not None:
            solver.krylov.stats = KrylovStats()
        x, report, reason = _minimize(solver, scene.x0)
    row = row_of(method, report, reason, proc_status_mib("VmHWM") - rss0)
    row["cpu_total"] = time.process_time() - cpu0
    row["cpu_first"] = cpu_first
    row["threads"] = args.threads
    for clock, clock_parts in parts.items():
        row[f"{clock}_parts_per_iteration"] = {k: v / max(report.iterations, 1)
                                               for k, v in clock_parts.items()}
    row["cpu_iteration"] = row["cpu_total"] / max(report.iterations, 1)
    if solver.krylov is not None:
        stats = solver.krylov.stats
        row.update(true_residual_max=max(stats.true_residuals, default=None),
                   setups=stats.setups, eigen_estimates=stats.eigen_estimates,
                   cg_per_solve=stats.iterations, indefinite_skips=stats.indefinite_skips)
    return row, np.asarray(x)


def _minimize(solver: ShellNewtonSolver, x0: np.ndarray
              ) -> tuple[np.ndarray, ShellSolveReport, str]:
    """``(x, report, reason)`` of one solve; a failed one gives its last state."""
    try:
        x, report = solver.minimize(x0)
        return x, report, report.reason
    except ShellSolveError as err:
        return err.x, err.report, f"failed: {err.report.reason}"


def cached_direct(scene: Scene, size: str, args: argparse.Namespace) -> tuple[dict, np.ndarray]:
    """The direct solve of the frame, run once and cached under :data:`CACHE`."""
    key = f"direct_{size}_{args.hessian}_{args.rtol:g}_{args.increment:g}_{args.iterations}"
    path = CACHE / f"{key}.npz"
    if path.exists() and not args.fresh_direct:
        data = np.load(path)
        row = json.loads(str(data["row"]))
        row["cached"] = True
        return row, data["x"]
    row, x = solve_row(scene, "direct", args)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, x=x, row=json.dumps(row))
    return row, x


def compare(row: dict, x: np.ndarray, ref: dict, x_ref: np.ndarray) -> None:
    """Add the differences to the direct solve: iterations, energy, max vertex distance."""
    row["extra_iterations"] = row["iterations"] - ref["iterations"]
    row["energy_gap"] = abs(row["energy"] - ref["energy"]) / abs(ref["energy"])
    row["max_vertex_diff"] = float(np.max(np.abs(x - x_ref)))


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


CONV_HEADER = (f"{'size':>5} {'method':>16} {'its':>4} {'+its':>4} {'cpu/it':>7} {'wall/it':>7} "
               f"{'cpu tot':>8} {'cpu 1st':>8} {'wall tot':>8} {'cg':>5} {'fb':>3} {'fact#':>5} "
               f"{'E gap':>8} "
               f"{'max dx':>8} {'true res':>8} {'|g| final':>10}")


def print_conv_row(size: str, r: dict) -> None:
    """One line of the to-tolerance table."""
    res = r.get("true_residual_max")
    print(f"{size:>5} {r['method']:>16} {r['iterations']:>4} {r['extra_iterations']:>+4d} "
          f"{r['cpu_iteration']:7.3f} {r['t_iteration']:7.3f} {r['cpu_total']:8.2f} "
          f"{r.get('cpu_first', r['cpu_total']):8.2f} {r['t_total']:8.2f} "
          f"{r['cg_iterations']:>5} {r['cg_fallbacks']:>3} "
          f"{r['factorizations']:>5} {r['energy_gap']:8.1e} {r['max_vertex_diff']:8.1e} "
          f"{'-' if res is None else f'{res:.1e}':>8} {r['grad_norms'][-1]:10.3e}", flush=True)


def iterate_size(size: str, args: argparse.Namespace) -> list[dict]:
    """Every method from the flat start of ``size`` for ``--iterations`` Newton iterations."""
    scene = build_scene(size, threads=args.threads)
    n = scene.energy.n_vertices
    rows = [run_method(scene, m, args) for m in args.methods]
    deviation(rows)
    for r in rows:
        r.update(size=size, n=n, setup_time=scene.setup_time)
        print_row(size, n, r)
    print_parts(rows)
    return rows


def print_parts(rows: list[dict]) -> None:
    """The ``--breakdown`` lines: CPU (and wall) seconds per Newton iteration of each part."""
    for r in rows:
        for clock in ("cpu", "wall"):
            parts = r.get(f"{clock}_parts_per_iteration") or {}
            if parts:
                print(f"  {clock}/it {r['method']}: " + " ".join(
                    f"{k.strip('_')} {v:.3f}"
                    for k, v in sorted(parts.items(), key=lambda kv: -kv[1])))


def converge_size(size: str, args: argparse.Namespace) -> list[dict]:
    """Every method on the warm-started frame of ``size`` to ``--to-tolerance``."""
    scene = frame_scene(size, args.increment, args.threads)
    ref, x_ref = cached_direct(scene, size, args)
    rows = [ref]
    for method in (m for m in args.methods if m != "direct"):
        row, x = solve_row(scene, method, args)
        compare(row, x, ref, x_ref)
        rows.append(row)
    compare(ref, x_ref, ref, x_ref)
    deviation(rows)
    for r in rows:
        r.update(size=size, n=scene.energy.n_vertices, setup_time=scene.setup_time)
        print_conv_row(size, r)
    print_parts(rows)
    return rows


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", default=["10k", "40k", "160k"], choices=list(LEVELS))
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    p.add_argument("--hessian", default="gauss_newton",
                   choices=["gauss_newton", "projected", "exact"])
    p.add_argument("--iterations", type=int, default=None,
                   help="Newton iterations per run (cap with --to-tolerance; default 8 / 100)")
    p.add_argument("--rtol", type=float, default=1e-12, help="stop earlier at this rtol")
    p.add_argument("--to-tolerance", type=float, default=None, metavar="RTOL",
                   help="warm-started frame solved to ||g|| <= RTOL ||g_0|| by every method")
    p.add_argument("--increment", type=float, default=0.005,
                   help="extra compression of the warm-started frame (--to-tolerance)")
    p.add_argument("--fresh-direct", action="store_true",
                   help="rerun the direct solve instead of reading its cached result")
    p.add_argument("--repeat", type=int, default=1,
                   help="solve each frame N times with the same solver; report the last")
    p.add_argument("--breakdown", action="store_true",
                   help="record process CPU time per part (evaluation, set-up parts, CG)")
    p.add_argument("--threads", type=int, default=1,
                   help="threads of the element kernels and of the multigrid level products "
                        "(ShellParams.threads, MultigridOptions.threads); CPU time then "
                        "exceeds wall time")
    p.add_argument("--quick", action="store_true", help="10k only")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.repeat < 1:
        p.error(f"--repeat: must be >= 1, got {args.repeat}")
    if args.quick:
        args.sizes = ["10k"]
    if args.to_tolerance is not None:
        args.rtol = args.to_tolerance
    if args.iterations is None:
        args.iterations = 8 if args.to_tolerance is None else 100
    if args.out is None:
        args.out = RESULTS if args.to_tolerance is None else \
            RESULTS.parent / f"iterative_{'_'.join(args.sizes)}_conv.json"
    return args


def main(argv: list[str] | None = None) -> None:
    """Run every (size, method), print the table, write the JSON."""
    args = parse_args(argv)
    PETSc.Sys.pushErrorHandler("python")
    print(HEADER if args.to_tolerance is None else CONV_HEADER)
    per_size = iterate_size if args.to_tolerance is None else converge_size
    out = [row for size in args.sizes for row in per_size(size, args)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"python": platform.python_version(), "petsc": PETSc.Sys.getVersion(),
            "cpus": os.cpu_count(), "omp_threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average_end": os.getloadavg(), "hessian": args.hessian,
            "iterations": args.iterations, "rtol": args.rtol,
            "to_tolerance": args.to_tolerance, "increment": args.increment,
            "units": "seconds per Newton iteration (t_* wall, cpu_iteration = process CPU "
                     "time, the better figure on a shared machine), peak_mib = VmHWM growth during "
                     "the run; dev = max relative deviation of ||g_k|| from the direct run"}
    args.out.write_text(json.dumps({"meta": meta, "rows": out}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
