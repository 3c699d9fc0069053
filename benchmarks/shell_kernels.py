"""Shell kernel benchmark: energy / gradient / Hessian of each term, assembly, per vertex.

For regular (icosphere) and irregular (jittered Delaunay plate) shells of about 10k, 40k,
160k and 640k vertices, times (numba compiled and warm, best of ``--repeat`` runs, one core):

* each term (edge membrane W_L, area membrane W_A, bending W_B, penalty W_P) at order 0
  (value), 1 (+ gradient) and 2 (+ local Hessian blocks), in microseconds per vertex;
* the generic assembly of the edge and hinge blocks (the default energy: k_A = 0) into the
  fixed CSR pattern, in microseconds per non-zero 3x3 block;
* the complete ``ShellEnergy.evaluate(x, order=2)`` (membrane + bending + penalty, penalty
  Hessian "low_rank" and, up to ``--assembled-max`` vertices, "assembled");
* topology / pattern build times and the process peak RSS after each mesh.

Each mesh is renumbered by every method of ``--reorder`` (:mod:`models.shell.reorder`;
default "none rcm" to show the effect of the locality ordering). ``x tgt`` is the ratio to
the targets of issue 3: 3 us per vertex for energy + gradient + Hessian of all terms (the
full ``evaluate``, assembly included), 1 us per non-zero 3x3 block for the assembly. The
full evaluate is timed with the flip barrier on (the ShellParams default, ``k_F = 1e3``) and
off (``k_F = 0``: membrane + bending + penalty, the terms the target names).

Usage::

    python benchmarks/shell_kernels.py --quick           # 10k only (while developing)
    python benchmarks/shell_kernels.py --sizes 10k 40k 160k 640k --assembled-max 0
    python benchmarks/shell_kernels.py --sizes 40k --clock cpu   # on a shared machine

Prints a table and writes benchmarks/results/shell_kernels.json (``--out`` another file).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numba
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from meshes.shells import icosphere, irregular_plate, perturb
from models.shell.assembly import StencilPattern, assemble
from models.shell.bending import hinge_bending
from models.shell.energy import ShellEnergy, ShellParams
from models.shell.membrane import area_membrane, edge_membrane
from models.shell.penalty import PenaltyOperator, penalty_term
from models.shell.reorder import REORDER_METHODS, reorder_mesh
from models.shell.rest import RestState
from models.shell.topology import ShellTopology

SIZES = {"10k": (5, 10_000), "40k": (6, 40_000), "160k": (7, 160_000), "640k": (8, 640_000)}
RESULTS = Path(__file__).resolve().parent / "results" / "shell_kernels.json"
TARGET_US_PER_VERTEX = 3.0
TARGET_US_PER_BLOCK = 1.0


CLOCKS: dict[str, Callable[[], float]] = {"wall": time.perf_counter, "cpu": time.process_time}
"""``--clock``: wall time (quiet machine) or the process CPU time, which leaves out the time
the process waits for a core on a shared machine (not the cache / memory-bandwidth contention)."""
_clock: list[Callable[[], float]] = [time.perf_counter]


def best_time(fn: Callable[[], object], repeat: int) -> float:
    """Best time of ``repeat`` calls after one warm-up call (seconds, ``--clock``)."""
    fn()
    clock = _clock[0]
    times = []
    for _ in range(repeat):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return min(times)


def peak_rss_mib() -> float:
    """Process peak resident set size (MiB, Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cluster_matrix(x: np.ndarray, rest: RestState, support: int, overlap: float,
                   seed: int) -> sp.csr_matrix:
    """Gaussian cluster weights (rows sum to 1) with ~``support`` vertices per cluster.

    ``c = overlap n / support`` random centres; ``sigma`` such that a disc of radius
    ``2 sigma`` holds ``support`` vertices; Euclidean distance (a stand-in for the clusters
    module's geodesic distance; only the sparsity matters here).
    """
    n = len(x)
    c = max(1, int(overlap * n / support))
    area_per_vertex = rest.rest_areas.sum() / n
    sigma = 0.5 * np.sqrt(support * area_per_vertex / np.pi)
    centres = np.random.default_rng(seed).choice(n, c, replace=False)
    dist = cKDTree(x[centres]).sparse_distance_matrix(cKDTree(x), 2 * sigma,
                                                      output_type="coo_matrix")
    w = sp.csr_matrix((np.exp(-dist.data**2 / (2 * sigma**2)), (dist.row, dist.col)), shape=(c, n))
    w = w + sp.csr_matrix((np.ones(c), (np.arange(c), centres)), shape=(c, n))  # d = 0 entries
    return sp.diags(1.0 / np.asarray(w.sum(axis=1)).ravel()) @ w


def make_mesh(kind: str, size: str, reorder: str) -> tuple[np.ndarray, np.ndarray]:
    """Regular icosphere or irregular plate of the requested size, renumbered by ``reorder``."""
    level, n = SIZES[size]
    points, faces = icosphere(level) if kind == "regular" else irregular_plate(n, seed=1)
    return reorder_mesh(points, faces, reorder)[:2]


def time_terms(x: np.ndarray, top: ShellTopology, rest: RestState, op: PenaltyOperator,
               repeat: int) -> dict[str, dict[str, float]]:
    """Seconds per call of each term at orders 0, 1, 2 (penalty: orders 0, 1)."""
    w = rest.hinge_weights
    terms: dict[str, Callable[[int], Any]] = {
        "membrane_edge": lambda o: edge_membrane(x, top.edges, rest.rest_lengths, order=o),
        "membrane_area": lambda o: area_membrane(x, top.faces, rest.rest_areas, order=o),
        "bending": lambda o: hinge_bending(x, top.hinges, rest.rest_angles, w, order=o),
        "penalty": lambda o: penalty_term(x, rest.positions, op, order=min(o, 1)),
    }
    out: dict[str, dict[str, float]] = {}
    for name, fn in terms.items():
        out[name] = {f"order{o}": best_time(lambda fn=fn, o=o: fn(o), repeat)  # type: ignore[misc]
                     for o in (0, 1, 2)}
    return out


def time_assembly(x: np.ndarray, top: ShellTopology, rest: RestState,
                  repeat: int) -> dict[str, float]:
    """Pattern build and assembly times (edges + hinges, as the default energy) and blocks."""
    t0 = time.perf_counter()
    pattern = StencilPattern.from_stencils([top.edges, top.hinges], top.n_vertices)
    build = time.perf_counter() - t0
    blocks: list[Any] = [edge_membrane(x, top.edges, rest.rest_lengths).blocks,
                         hinge_bending(x, top.hinges, rest.rest_angles, rest.hinge_weights).blocks]
    contributions = list(zip(pattern.maps, blocks, strict=True))
    t = best_time(lambda: assemble(pattern, contributions), repeat)
    return {"pattern_build_s": build, "assemble_s": t, "n_blocks": pattern.n_blocks,
            "us_per_block": 1e6 * t / pattern.n_blocks}


def time_energy(x: np.ndarray, top: ShellTopology, rest: RestState, h: sp.csr_matrix,
                mode: str, hessian_modes: list[str], repeat: int,
                k_F: float = 1e3) -> dict[str, float]:
    """Setup and evaluate(order=2) time of the full energy (W_L + W_B + W_P [+ W_F])."""
    t0 = time.perf_counter()
    params = ShellParams(penalty_hessian=mode, k_F=k_F)  # type: ignore[arg-type]
    energy = ShellEnergy(top, rest, params, H=h)
    out = {"setup_s": time.perf_counter() - t0, "n_blocks": energy.pattern.n_blocks, "k_F": k_F}
    for hm in hessian_modes:
        t = best_time(lambda hm=hm: energy.evaluate(x, order=2, hessian=hm),  # type: ignore[misc]
                      repeat)
        out[f"{hm}_us_per_vertex"] = 1e6 * t / top.n_vertices
    return out


def bench_one(kind: str, size: str, reorder: str,
              args: argparse.Namespace) -> dict[str, object]:
    """All measurements for one mesh."""
    p, f = make_mesh(kind, size, reorder)
    t0 = time.perf_counter()
    top = ShellTopology.from_faces(f, len(p))
    t_top = time.perf_counter() - t0
    rest = RestState.from_positions(top, p)
    scale = float(np.median(rest.rest_lengths))
    x = perturb(p, 0.05 * scale, seed=2)
    h = cluster_matrix(p, rest, args.support, args.overlap, seed=3)
    n = top.n_vertices
    terms = time_terms(x, top, rest, PenaltyOperator.from_matrix(h, n), args.repeat)
    rec: dict[str, object] = {
        "kind": kind, "size": size, "reorder": reorder, "n_vertices": n, "n_edges": top.n_edges,
        "n_faces": top.n_faces, "n_hinges": int(top.hinges.shape[0]), "topology_s": t_top,
        "terms_us_per_vertex": {k: {o: 1e6 * v / n for o, v in d.items()}
                                for k, d in terms.items()},
        "assembly": time_assembly(x, top, rest, args.repeat),
        "energy_low_rank": time_energy(x, top, rest, h, "low_rank", args.modes, args.repeat),
        "energy_low_rank_no_barrier": time_energy(x, top, rest, h, "low_rank", args.modes[:1],
                                                  args.repeat, k_F=0.0),
        "n_clusters": h.shape[0], "H_nnz": h.nnz,
    }
    if n <= args.assembled_max:
        rec["energy_assembled"] = time_energy(x, top, rest, h, "assembled", args.modes[:1],
                                              args.repeat)
    rec["peak_rss_mib"] = peak_rss_mib()
    return rec


def print_row(r: dict[str, Any]) -> None:
    """One table block per mesh."""
    t = r["terms_us_per_vertex"]
    a = r["assembly"]
    print(f"\n{r['kind']:>9} {r['size']:>5} reorder {r['reorder']:<6} n={r['n_vertices']:>7} "
          f"topology {r['topology_s']:.2f} s  peak RSS {r['peak_rss_mib']:.0f} MiB")
    print(f"  {'term':<14}{'value':>10}{'+grad':>10}{'+hess':>10}   (us / vertex)")
    for name, d in t.items():
        print(f"  {name:<14}{d['order0']:>10.3f}{d['order1']:>10.3f}{d['order2']:>10.3f}")
    print(f"  assembly: {a['n_blocks']} blocks, {a['assemble_s'] * 1e3:.1f} ms = "
          f"{a['us_per_block']:.3f} us/block (x tgt {a['us_per_block'] / TARGET_US_PER_BLOCK:.2f});"
          f" pattern build {a['pattern_build_s']:.2f} s")
    for key in ("energy_low_rank", "energy_low_rank_no_barrier", "energy_assembled"):
        e = r.get(key)
        if not isinstance(e, dict):
            continue
        modes = ", ".join(f"{k[:-14]} {v:.3f} (x tgt {v / TARGET_US_PER_VERTEX:.2f})"
                          for k, v in e.items() if k.endswith("_us_per_vertex"))
        print(f"  evaluate(order=2) {key[7:]:<18} k_F={e['k_F']:g}: {modes} us/vertex "
              f"({e['n_blocks']} blocks, setup {e['setup_s']:.2f} s)")


def main() -> None:
    """Parse options, run, print, write JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--quick", action="store_true", help="10k only")
    ap.add_argument("--kinds", nargs="+", default=["regular", "irregular"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--modes", nargs="+", default=["exact", "gauss_newton", "projected"],
                    help="Hessian modes timed for the full evaluate (first one also 'assembled')")
    ap.add_argument("--support", type=int, default=30, help="vertices per cluster")
    ap.add_argument("--overlap", type=float, default=2.0, help="clusters per vertex")
    ap.add_argument("--assembled-max", type=int, default=200_000,
                    help="largest n for the 'assembled' penalty Hessian")
    ap.add_argument("--clock", default="wall", choices=list(CLOCKS),
                    help="wall time, or process CPU time on a shared machine")
    ap.add_argument("--reorder", nargs="+", default=["none", "rcm"],
                    choices=list(REORDER_METHODS), help="vertex renumberings to compare")
    ap.add_argument("--out", type=Path, default=RESULTS, help="JSON file to write")
    args = ap.parse_args()
    sizes = ["10k"] if args.quick else args.sizes
    _clock[0] = CLOCKS[args.clock]
    numba.set_num_threads(1)
    records = []
    for size in sizes:
        for kind in args.kinds:
            for reorder in args.reorder:
                rec = bench_one(kind, size, reorder, args)
                print_row(rec)
                records.append(rec)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"python": platform.python_version(), "numpy": np.__version__,
            "numba": numba.__version__, "machine": platform.machine(),
            "cpu_count": os.cpu_count(), "repeat": args.repeat, "support": args.support,
            "overlap": args.overlap, "clock": args.clock,
            "target_us_per_vertex": TARGET_US_PER_VERTEX,
            "target_us_per_block": TARGET_US_PER_BLOCK, "load_average_end": os.getloadavg()}
    args.out.write_text(json.dumps({"meta": meta, "results": records}, indent=2))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
