"""Sparse direct solve benchmark for the shell Newton system, per backend and size.

For regular (icosphere) and irregular (jittered Delaunay plate) shells of about 10k, 40k,
160k and 640k vertices, a realistic shell Hessian is assembled by ``ShellEnergy`` at a
perturbed state (membrane + bending, Gauss-Newton local Hessians so the matrix is SPD, plus
the cluster penalty), and each backend is timed (one core, OMP_NUM_THREADS=1):

* ``first``: first factorisation = symbolic analysis + numeric (split by PETSc log events);
* ``refact``: refactorisation with new values (the Hessian at a second state), analysis reused
  (``cpu``: its process CPU time, which leaves out the waits for a core on a shared machine);
* ``solve``: forward/backward substitution;
* ``newton_it``: one Newton iteration = evaluate (order 2) + refact + solve + one energy
  value (the accepted full step of the line search);
* ``x tgt``: (refact + solve) over the target 1.3 x CHOLMOD (:data:`TARGET_S`: 0.455 s at
  10k, 2.99 s at 40k, 19.5 s at 160k = 1.3 x the lower CHOLMOD figure 15 s; none at 640k);
* factor entries / MUMPS memory, and the growth of the process peak RSS during that backend
  (``dRSS`` = VmHWM - VmRSS at its start, VmHWM reset through /proc/self/clear_refs), and
  the process peak RSS of the whole case (``peak``: mesh, energy, Hessians and the solver;
  target < 12 GiB at 640k).

The mesh vertices are renumbered once by ``--reorder`` (:mod:`models.shell.reorder`, default
RCM) before the topology is built, as the application should do; the METIS ordering of
MUMPS makes the factorisation itself independent of the vertex numbering (measured: the same
factor entries), only the kernels and the assembly gain. The true residual of the augmented
system is computed as ``A dx + G^T (G dx) - b`` without forming ``G^T G``: session 1 formed
``A + G^T G`` (250 M entries at 160k) for the check, which was most of the 17 GiB peak that
the augmented case reported at 160k.

Three systems (``--systems``):

* ``local``: membrane + bending + ``k_P I`` (a diagonal penalty, c = n clusters of one
  vertex): the sparsest shell pattern, 1-ring + hinge-opposite vertex blocks;
* ``assembled``: membrane + bending + the cluster penalty ``2 k_P (H^T H) (x) I_3`` merged
  into the pattern (fills in: every pair of vertices sharing a cluster), only up to
  ``--assembled-max`` vertices and only with :data:`ASSEMBLED_BACKENDS`;
* ``augmented``: membrane + bending with the penalty as the low-rank factor G, solved as
  ``[[A, G^T], [G, -I]]`` (LDL^T / LU only).

Clusters: ``n / --cluster-ratio`` centres on a voxel grid, Gaussian weights of the Euclidean
distance (sigma = 2 r / pi, cut at 2 sigma, rows normalised), a cheap stand-in for
``models.embedding.clusters`` (whose edge-path FPS takes minutes beyond 40k vertices) with
the same sparsity (about 75 vertices per cluster).

Usage::

    python benchmarks/shell_solve.py --quick                 # 10k only (while developing)
    python benchmarks/shell_solve.py --sizes 10k 40k 160k 640k
    python benchmarks/shell_solve.py --sizes 640k --systems local \
        --backends mumps-chol-aij mumps-chol-blr mumps-chol-ooc   # the 640k memory check

Prints a table and writes benchmarks/results/shell_solve.json. Reference (CHOLMOD, one
core, this machine): 0.35 s (10k vertices), 2.3 s (40k), 15-18 s (160k).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from meshes.shells import icosphere, irregular_plate, perturb
from models.backend import PETSc
from models.shell.energy import PenaltyHessian, ShellEnergy, ShellParams
from models.shell.reorder import REORDER_METHODS, reorder_mesh
from models.shell.rest import RestState
from models.shell.topology import ShellTopology
from solvers.linear import (
    AugmentedPenaltySolver,
    LinearSolverOptions,
    SparseDirectSolver,
    true_residual,
)

SIZES = {"10k": (5, 10_000), "40k": (6, 40_000), "160k": (7, 160_000), "640k": (8, 640_000)}
RESULTS = Path(__file__).resolve().parent / "results" / "shell_solve.json"
# mumps_blr=False: the full-rank factor (the default LinearSolverOptions use BLR at 1e-10)
BACKENDS: dict[str, LinearSolverOptions] = {
    "mumps-chol-aij": LinearSolverOptions("mumps", "cholesky", "aij", mumps_blr=False),
    "mumps-chol-sbaij": LinearSolverOptions("mumps", "cholesky", "sbaij", mumps_blr=False),
    "mumps-ldlt-aij": LinearSolverOptions("mumps", "ldlt", "aij", mumps_blr=False),
    "mumps-ldlt-sbaij": LinearSolverOptions("mumps", "ldlt", "sbaij", mumps_blr=False),
    "mumps-chol-amd": LinearSolverOptions("mumps", "cholesky", "aij", ordering="amd",
                                          mumps_blr=False),
    "mumps-chol-blr": LinearSolverOptions("mumps", "cholesky", "aij"),  # the default options
    "mumps-ldlt-blr": LinearSolverOptions("mumps", "ldlt", "sbaij"),
    "mumps-chol-ooc": LinearSolverOptions("mumps", "cholesky", "aij", mumps_out_of_core=True),
    # (BLR on, factors on disk)
    "mumps-chol-scotch": LinearSolverOptions("mumps", "cholesky", "aij", ordering="scotch",
                                             mumps_blr=False),
    "mumps-chol-pord": LinearSolverOptions("mumps", "cholesky", "aij", ordering="pord",
                                           mumps_blr=False),
    "petsc-chol-nd": LinearSolverOptions("petsc", "cholesky", "aij"),
    "superlu_dist-lu": LinearSolverOptions("superlu_dist", "lu", "aij"),
    "scipy-splu-sym": LinearSolverOptions("scipy", "cholesky", "aij"),
}
SLOW = ("petsc-chol-nd", "superlu_dist-lu", "scipy-splu-sym")
EXPLORATORY = ("mumps-chol-amd", "mumps-chol-ooc", "mumps-chol-scotch", "mumps-chol-pord")
"""Run only when named in ``--backends`` (orderings that lose to METIS, out-of-core)."""
TARGET_S = {"10k": 1.3 * 0.35, "40k": 1.3 * 2.3, "160k": 1.3 * 15.0}
"""Target of the linear solve of a Newton iteration: 1.3 x CHOLMOD (issue 3), seconds."""
ASSEMBLED_BACKENDS = ("mumps-chol-aij", "mumps-chol-sbaij")
"""The filled-in assembled penalty system (27M nonzeros at 10k vertices) is only run with
these; the others take minutes on it."""


def proc_status_mib(key: str) -> float:
    """A memory line of /proc/self/status ("VmHWM" peak, "VmRSS" current) in MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{key}:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def reset_peak_rss() -> None:
    """Reset VmHWM to the current RSS (Linux: write 5 to /proc/self/clear_refs)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def make_mesh(kind: str, size: str, reorder: str = "rcm") -> tuple[np.ndarray, np.ndarray]:
    """Regular icosphere of ``SIZES[size][0]`` levels or irregular plate of ~n vertices."""
    level, n = SIZES[size]
    points, faces = icosphere(level) if kind == "regular" else irregular_plate(n, seed=1)
    return reorder_mesh(points, faces, reorder)[:2]


def cluster_matrix(points: np.ndarray, ratio: int) -> sp.csr_matrix:
    """Gaussian weights (Euclidean, cut at 2 sigma, rows sum to 1) of ~n/ratio voxel centres."""
    n = len(points)
    extent = np.ptp(points, axis=0)
    dims = int(np.count_nonzero(extent > 1e-12 * extent.max()))
    volume = np.prod(extent[extent > 1e-12 * extent.max()])
    spacing = (volume * ratio / n) ** (1.0 / dims) * (0.6 if dims == 3 else 1.0)
    cells = np.floor((points - points.min(0)) / spacing).astype(np.int64)
    _, centres = np.unique(cells, axis=0, return_index=True)
    sigma = 2.0 * spacing / np.pi
    tree = cKDTree(points)
    rows, cols, vals = [], [], []
    for c, members in enumerate(tree.query_ball_point(points[centres], 2.0 * sigma)):
        d2 = np.sum((points[members] - points[centres[c]]) ** 2, axis=1)
        w = np.exp(-d2 / (2.0 * sigma**2))
        rows.append(np.full(len(members), c))
        cols.append(members)
        vals.append(w / w.sum())
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(len(centres), n))


def build_energy(points: np.ndarray, faces: np.ndarray, system: str,
                 h: sp.csr_matrix) -> ShellEnergy:
    """ShellEnergy (k_L 1e3, k_B 1e-1, k_P 1e3, Gauss-Newton) for one of the three systems."""
    topo = ShellTopology.from_faces(faces, len(points))
    rest = RestState.from_positions(topo, points)
    penalty: PenaltyHessian = "low_rank" if system == "augmented" else "assembled"
    params = ShellParams(k_L=1e3, k_B=1e-1, k_P=1e3, hessian_mode="gauss_newton",
                         penalty_hessian=penalty)
    cluster = sp.identity(len(points), format="csr") if system == "local" else h
    return ShellEnergy(topo, rest, params, H=cluster)


def timed(fn):  # noqa: ANN001, ANN201
    """(result, seconds) of ``fn()``."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def bench_backend(name: str, opts: LinearSolverOptions, size: str, evals: list,
                  t_eval: float, t_value: float, system: str) -> dict:
    """Time first factorisation, refactorisation and solve of one backend; check residuals."""
    reset_peak_rss()
    rss_start = proc_status_mib("VmRSS")
    a0, a1 = evals[0].hess, evals[1].hess
    g = evals[0].penalty_factor
    rhs = -evals[1].grad
    solver: AugmentedPenaltySolver | SparseDirectSolver
    if system == "augmented":
        aug = AugmentedPenaltySolver(a0, g, opts)
        first, solver = aug.factorize(a0, g), aug
        cpu0 = time.process_time()
        refact = aug.factorize(a1, g)
    else:
        plain = SparseDirectSolver(a0, opts)
        first, solver = plain.factorize(a0), plain
        cpu0 = time.process_time()
        refact = plain.factorize(a1)
    refact_cpu = time.process_time() - cpu0
    dx, t_solve = timed(lambda: solver.solve(rhs))
    for _ in range(2):
        t_solve = min(t_solve, timed(lambda: solver.solve(rhs))[1])
    residual = true_residual(a1, dx, rhs) if system != "augmented" else \
        float(np.linalg.norm(a1 @ dx + g.T @ (g @ dx) - rhs) / np.linalg.norm(rhs))
    solver.destroy()
    t_first = first.analysis_time + first.numeric_time
    t_refact = refact.numeric_time + refact.analysis_time
    target = TARGET_S.get(size)
    return {"backend": name, "ok": bool(first.success and refact.success),
            "analysis": first.analysis_time, "first_numeric": first.numeric_time,
            "first": t_first, "refact": t_refact, "refact_cpu": refact_cpu,
            "reused_analysis": refact.reused_analysis, "solve": t_solve,
            "newton_it": t_eval + t_refact + t_solve + t_value,
            "ratio_to_target": (t_refact + t_solve) / target if target else None,
            "residual": residual, "negative_pivots": refact.negative_pivots,
            "factor_nnz": refact.factor_nnz, "mumps_mb": refact.memory_mb,
            "peak_rss_delta_mib": proc_status_mib("VmHWM") - rss_start}


def evaluate_states(energy: ShellEnergy, points: np.ndarray, h_scale: float
                    ) -> tuple[list, dict[str, float]]:
    """Two perturbed states (10 % / 12 % of the mean edge), their order-2 evaluations, timings.

    Timings (best of 2, seconds): ``t_value`` order 0, ``t_grad`` order 1, ``t_eval`` order 2
    (value, gradient, local Hessians and their assembly into the fixed pattern).
    """
    states = [perturb(points, 0.10 * h_scale, seed=1), perturb(points, 0.12 * h_scale, seed=2)]
    energy.set_target(points)
    evals = [energy.evaluate(x, order=2) for x in states]
    times = {f"t_{name}": min(timed(lambda o=order: energy.evaluate(states[1], order=o))[1]
                              for _ in range(2))
             for name, order in (("value", 0), ("grad", 1), ("eval", 2))}
    return evals, times


def mean_edge(points: np.ndarray, faces: np.ndarray) -> float:
    """Mean edge length of the mesh (over face edges, with repeats)."""
    e = points[faces[:, [1, 2, 0]]] - points[faces]
    return float(np.mean(np.linalg.norm(e, axis=2)))


def backends_for(system: str, names: list[str], size: str, slow_max: str) -> list[str]:
    """Backends that apply to ``system`` (no Cholesky on the indefinite augmented matrix)."""
    out = []
    for name in names:
        opts = BACKENDS.get(name)
        if opts is None:  # augmented-only backend ("mumps-lu-aug"), added below
            continue
        if system == "augmented" and opts.symmetric == "cholesky":
            continue
        if name in SLOW and SIZES[size][1] > SIZES[slow_max][1]:
            continue
        if system == "assembled" and name not in ASSEMBLED_BACKENDS:
            continue
        out.append(name)
    if system == "augmented":
        out += [n for n in ("mumps-lu-aug",) if n not in out]
    return out


def run_case(kind: str, size: str, system: str, args: argparse.Namespace) -> list[dict]:
    """All backends on one mesh / system; returns the result rows."""
    reset_peak_rss()
    points, faces = make_mesh(kind, size, args.reorder)
    h = cluster_matrix(points, args.cluster_ratio)
    energy, t_build = timed(lambda: build_energy(points, faces, system, h))
    evals, times = evaluate_states(energy, points, mean_edge(points, faces))
    a = evals[0].hess
    g = evals[0].penalty_factor
    info = {"mesh": kind, "size": size, "vertices": len(points), "system": system,
            "dofs": a.shape[0], "nnz": int(a.nnz + (2 * g.nnz + g.shape[0] if g is not None
                                                    else 0)),
            "clusters": int(h.shape[0]), "cluster_support": float(h.getnnz(axis=1).mean()),
            "t_build": t_build, **times, "load_average_1min": os.getloadavg()[0]}
    print(f"# {kind} {size} {system}: build {t_build:.2f} s; value / +grad / +hess+assembly "
          f"{times['t_value']:.3f} / {times['t_grad']:.3f} / {times['t_eval']:.3f} s = "
          f"{1e6 * times['t_eval'] / len(points):.2f} us/vertex; "
          f"load {info['load_average_1min']:.1f}", flush=True)
    rows = []
    for name in backends_for(system, args.backends, size, args.slow_max):
        opts = BACKENDS.get(name) or LinearSolverOptions("mumps", "lu", "aij", mumps_blr=False)
        row = {**info, **bench_backend(name, opts, size, evals, times["t_eval"],
                                        times["t_value"], system)}
        row["peak_rss_mib"] = proc_status_mib("VmHWM")
        print_row(row)
        rows.append(row)
    return rows


HEADER = (f"{'mesh':9}{'size':>5}{'system':>10}{'dofs':>9}{'nnz':>11} {'backend':18}"
          f"{'analysis':>9}{'first':>8}{'refact':>8}{'cpu':>7}{'solve':>7}{'newton':>8}{'resid':>9}"
          f"{'x tgt':>6}{'fact nnz':>11}{'MB':>7}{'dRSS':>7}{'peak':>7}")


def print_row(r: dict) -> None:
    """One table line (seconds, MB)."""
    mb = f"{r['mumps_mb']:.0f}" if r["mumps_mb"] is not None else "-"
    nnz = f"{r['factor_nnz']:.3g}" if r["factor_nnz"] is not None else "-"
    ratio = f"{r['ratio_to_target']:.2f}" if r["ratio_to_target"] is not None else "-"
    print(f"{r['mesh']:9}{r['size']:>5}{r['system']:>10}{r['dofs']:>9}{r['nnz']:>11} "
          f"{r['backend']:18}{r['analysis']:9.3f}{r['first']:8.3f}{r['refact']:8.3f}"
          f"{r['refact_cpu']:7.3f}"
          f"{r['solve']:7.3f}{r['newton_it']:8.3f}{r['residual']:9.1e}{ratio:>6}{nnz:>11}"
          f"{mb:>7}{r['peak_rss_delta_mib']:7.0f}{r['peak_rss_mib']:7.0f}"
          + ("" if r["ok"] else "  FAILED"), flush=True)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line: sizes, meshes, systems, backends."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    p.add_argument("--quick", action="store_true", help="10k only")
    p.add_argument("--meshes", nargs="+", default=["regular", "irregular"],
                   choices=["regular", "irregular"])
    p.add_argument("--systems", nargs="+", default=["local", "assembled", "augmented"],
                   choices=["local", "assembled", "augmented"])
    p.add_argument("--backends", nargs="+",
                   default=[b for b in BACKENDS if b not in EXPLORATORY],
                   choices=[*BACKENDS, "mumps-lu-aug"])
    p.add_argument("--assembled-max", default="10k", choices=list(SIZES),
                   help="largest size for the assembled (filled-in) penalty system")
    p.add_argument("--slow-max", default="160k", choices=list(SIZES),
                   help="largest size for petsc / superlu_dist / scipy")
    p.add_argument("--cluster-ratio", type=int, default=25, help="vertices per cluster centre")
    p.add_argument("--reorder", default="rcm", choices=list(REORDER_METHODS),
                   help="vertex renumbering applied to the mesh (models/shell/reorder.py)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.quick:
        args.sizes = ["10k"]
    return args


def main(argv: list[str] | None = None) -> None:
    """Run every (size, mesh, system) case, print the table, write the JSON."""
    args = parse_args(argv)
    PETSc.Sys.pushErrorHandler("python")
    print(HEADER)
    rows: list[dict] = []
    for size in args.sizes:
        for kind in args.meshes:
            for system in args.systems:
                if system == "assembled" and SIZES[size][1] > SIZES[args.assembled_max][1]:
                    continue
                rows += run_case(kind, size, system, args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"python": platform.python_version(), "petsc": PETSc.Sys.getVersion(),
            "machine": platform.machine(), "omp_threads": os.environ.get("OMP_NUM_THREADS"),
            "cpus": os.cpu_count(), "load_average_end": os.getloadavg(),
            "reference_cholmod_s": {"10k": 0.35, "40k": 2.3, "160k": "15-18"},
            "target_s": TARGET_S, "reorder": args.reorder,
            "units": "seconds; MB = MUMPS INFOG(22); dRSS = peak RSS growth (MiB) per "
                     "backend; peak = process VmHWM (MiB) since the start of the case"}
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
