"""Cluster set-up time (:mod:`models.embedding.clusters`) against the shell size, growth fits.

The shell is a flat ``C x C`` grid plate (:func:`meshes.shells.grid_plate`, alternate
diagonals) with ``n = (C + 1)^2`` vertices: C = 100 / 200 / 400 / 800 gives the 10k / 40k /
160k / 640k sizes of :mod:`benchmarks.scaling` (same n, no subdivision hierarchy to build).
The clusters are sized as there, ``c = n / 75`` farthest-point centres. Stages, each timed in
wall and process CPU seconds (CPU is the fairer figure on a shared machine):

* ``edge_graph``: :func:`edge_graph`;
* ``centres_fps``: :func:`farthest_point_centres` with ``count = n / 75`` (spacing r);
* ``gaussian_weights``: :func:`gaussian_weights` with ``sigma = 2 r / pi`` (the default);
* ``partition``: :func:`nearest_centre_partition`;
* ``min_singular_value``: :func:`smallest_singular_value` of H;
* ``centres_bfs``: :func:`greedy_bfs_centres` at the spacing r (the "bfs" method; not part
  of the default :func:`build_clusters`; ``--no-bfs`` skips it).

``build_clusters`` is the sum of the first five (what :func:`build_clusters` runs with
``ClusterOptions(count=n // 75)``). Every size runs in its own process (its own peak RSS),
after a warm-up on a small plate (numba compilation or cache load is not timed), and is
killed after ``--timeout`` seconds. Rows carry a ``--label`` (e.g. "before" / "after" a change)
and ``--append`` keeps the rows of other labels / sizes already in ``--out``.

Growth exponents ``y ~ n^p`` are least-squares lines on log-log (``np.polyfit``) over the sizes
of one label, with the local slopes between consecutive sizes.

Usage::

    python benchmarks/cluster_setup.py --quick                       # 10k, 40k
    python benchmarks/cluster_setup.py --sizes 10k 40k 160k 640k --label after
    python benchmarks/cluster_setup.py --sizes 640k --label after --append
    python benchmarks/cluster_setup.py --refit                       # refit the JSON only

Prints a table and writes benchmarks/results/cluster_setup.json (rewritten after every size).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import scipy.sparse as sp

from benchmarks.shell_solve import proc_status_mib
from benchmarks.timing import Timings, power_fit, stopwatch
from meshes.shells import grid_plate
from models.embedding.clusters import (
    edge_graph,
    farthest_point_centres,
    gaussian_weights,
    greedy_bfs_centres,
    nearest_centre_partition,
    smallest_singular_value,
)

RESULTS = Path(__file__).resolve().parent / "results" / "cluster_setup.json"
SIZES: dict[str, int] = {"2.5k": 50, "10k": 100, "40k": 200, "160k": 400, "640k": 800}
CLUSTER_RATIO = 75  # vertices per cluster (as benchmarks.scaling)
BUILD_STAGES = ("edge_graph", "centres_fps", "gaussian_weights", "partition",
                "min_singular_value")
STAGE_COLUMNS = ("edge_graph", "centres_fps", "gaussian_weights", "partition",
                 "min_singular_value", "build_clusters", "centres_bfs")
SHORT = {"edge_graph": "graph", "centres_fps": "fps", "gaussian_weights": "weights",
         "partition": "partition", "min_singular_value": "svd", "build_clusters": "build",
         "centres_bfs": "bfs"}


@dataclass
class Built:
    """What the timed stages of :func:`build_stages` produce."""

    graph: sp.csr_matrix
    centres: np.ndarray
    spacing: float
    h: sp.csr_matrix
    partition: np.ndarray
    min_singular_value: float


def build_stages(v: np.ndarray, f: np.ndarray, t: Timings) -> Built:
    """The stages of :func:`build_clusters` at ``n / 75`` centres, each timed into ``t``.

    Shared with ``benchmarks/scaling.py --clusters-study``.
    """
    with stopwatch(t, "edge_graph"):
        graph = edge_graph(v, f)
    with stopwatch(t, "centres_fps"):
        centres, r = farthest_point_centres(graph, 0, max(1, len(v) // CLUSTER_RATIO), None)
    with stopwatch(t, "gaussian_weights"):
        h = gaussian_weights(graph, centres, 2.0 * r / np.pi)
    with stopwatch(t, "partition"):
        partition = nearest_centre_partition(graph, centres)
    with stopwatch(t, "min_singular_value"):
        smin = smallest_singular_value(h)
    return Built(graph, centres, r, h, partition, smin)


def stages(cells: int, t: Timings, bfs: bool = True) -> dict:
    """Run (and time into ``t``) every stage on the ``cells x cells`` plate; a summary."""
    v, f = grid_plate(cells, cells)
    b = build_stages(v, f, t)
    graph, centres, r, h, partition, smin = (b.graph, b.centres, b.spacing, b.h, b.partition,
                                             b.min_singular_value)
    t["build_clusters"] = {k: sum(t[s][k] for s in BUILD_STAGES) for k in ("wall", "cpu")}
    out = {"n": len(v), "clusters": int(centres.size), "spacing": r, "nnz": int(h.nnz),
           "min_singular_value": smin, "partition_checksum": int(partition.sum()),
           "centres_checksum": int(centres.sum())}
    if bfs:
        with stopwatch(t, "centres_bfs"):
            bfs_centres = greedy_bfs_centres(graph, 0, r)
        out |= {"bfs_clusters": int(bfs_centres.size), "bfs_checksum": int(bfs_centres.sum())}
    return out


def run_one(size: str, label: str, bfs: bool) -> dict:
    """One size in this process (after an untimed warm-up): the JSON row."""
    stages(20, Timings())  # warm-up: numba compilation / cache load
    load_start, t = os.getloadavg(), Timings()
    summary = stages(SIZES[size], t, bfs)
    return {"size": size, "label": label, **summary, "stages": t,
            "peak_mib": proc_status_mib("VmHWM"), "load_start": load_start,
            "load_end": os.getloadavg()}


def run_in_subprocess(size: str, label: str, timeout: float, bfs: bool) -> dict | None:
    """``run_one`` in a fresh interpreter; None if it failed or timed out."""
    cmd = [sys.executable, __file__, "--one", size, "--label", label]
    cmd += [] if bfs else ["--no-bfs"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        print(f"{size}: timed out after {timeout:.0f} s", flush=True)
        return None
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        print(f"{size}: failed (exit {proc.returncode}): {proc.stderr.strip()[-400:]}",
              flush=True)
        return None
    return json.loads(lines[-1])


def exponents(rows: list[dict]) -> dict[str, dict[str, dict]]:
    """CPU-time fits of every stage, per label (labels with at least two sizes)."""
    out: dict[str, dict[str, dict]] = {}
    for label in sorted({r["label"] for r in rows}):
        sel = sorted((r for r in rows if r["label"] == label), key=lambda r: r["n"])
        if len(sel) < 2:
            continue
        out[label] = {}
        for stage in STAGE_COLUMNS:  # over the sizes that ran the stage
            have = [r for r in sel if stage in r["stages"]]
            n = np.array([r["n"] for r in have], dtype=float)
            y = np.array([r["stages"][stage]["cpu"] for r in have], dtype=float)
            if len(have) >= 2 and np.all(y > 0):
                out[label][stage] = power_fit(n, y)
    return out


def print_header() -> None:
    """Column titles of :func:`print_row`."""
    cols = " ".join(f"{SHORT[s]:>9}" for s in STAGE_COLUMNS)
    print("process CPU seconds per stage (build = graph + fps + weights + partition + svd)")
    print(f"{'label':>8} {'size':>5} {'n':>7} {'c':>5} {cols} {'peakMiB':>8} {'load':>5}")


def print_row(r: dict) -> None:
    """One line of the table: CPU seconds per stage."""
    cols = " ".join(f"{r['stages'][s]['cpu']:9.3f}" if s in r["stages"] else f"{'-':>9}"
                    for s in STAGE_COLUMNS)
    print(f"{r['label']:>8} {r['size']:>5} {r['n']:>7} {r['clusters']:>5} {cols} "
          f"{r['peak_mib']:8.0f} {r['load_end'][0]:5.2f}", flush=True)


def print_fits(fits: dict[str, dict[str, dict]]) -> None:
    """The fitted CPU exponents with the local slopes."""
    print("CPU growth exponents p (y ~ n^p, np.polyfit on log-log), local slopes:")
    for label, fit in fits.items():
        for stage in STAGE_COLUMNS:
            if stage in fit:
                v = fit[stage]
                local = " ".join(f"{s:.2f}" for s in v["local"])
                print(f"  {label:>8} {stage:>18}: p = {v['p']:.3f}  "
                      f"max res {v['max_log_residual']:.3f}  local [{local}]")


def merge(old: list[dict], new: list[dict]) -> list[dict]:
    """``old`` rows not replaced by a ``new`` row of the same (size, label), plus ``new``."""
    keys = {(r["size"], r["label"]) for r in new}
    kept = [r for r in old if (r["size"], r["label"]) not in keys]
    return sorted(kept + new, key=lambda r: (r["label"], r["n"]))


def save(path: Path, rows: list[dict]) -> dict[str, dict[str, dict]]:
    """Write the rows, the fits and the provenance as JSON; return the fits."""
    fits = exponents(rows)
    meta = {"python": platform.python_version(), "cpus": os.cpu_count(),
            "omp_threads": os.environ.get("OMP_NUM_THREADS"),
            "load_average_end": os.getloadavg(), "cluster_ratio": CLUSTER_RATIO,
            "mesh": "grid_plate(C, C), alternate diagonals, SIZES = cells per side",
            "units": "seconds (wall and process CPU) per stage; peak_mib = VmHWM of the "
                     "size's process; exponents fitted on CPU time by np.polyfit on log-log",
            "exponents": fits}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    return fits


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", default=["10k", "40k", "160k"], choices=list(SIZES))
    p.add_argument("--label", default="current", help="tag of the rows (e.g. before, after)")
    p.add_argument("--quick", action="store_true", help="10k and 40k only")
    p.add_argument("--append", action="store_true",
                   help="merge with the rows already in --out (same size + label replaced)")
    p.add_argument("--refit", action="store_true", help="run nothing: refit --out")
    p.add_argument("--timeout", type=float, default=180.0, help="seconds per size")
    p.add_argument("--bfs", action=argparse.BooleanOptionalAction, default=True,
                   help="time greedy_bfs_centres too")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.quick:
        args.sizes = ["10k", "40k"]
    if args.refit:
        args.append, args.sizes = True, []
    return args


def main(argv: list[str] | None = None) -> None:
    """Run every size in its own process, print the table and exponents, write the JSON."""
    args = parse_args(argv)
    if args.one is not None:
        print(json.dumps(run_one(args.one, args.label, args.bfs)))
        return
    old = (json.loads(args.out.read_text())["rows"]
           if args.append and args.out.is_file() else [])
    new: list[dict] = []
    print_header()
    for r in old:
        print_row(r)
    for size in args.sizes:
        result = run_in_subprocess(size, args.label, args.timeout, args.bfs)
        if result is not None:
            print_row(result)
            new.append(result)
            save(args.out, merge(old, new))
    print_fits(save(args.out, merge(old, new)))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
