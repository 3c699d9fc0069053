"""Strong scaling of the split shell: measured at 1 to 4 ranks, modelled to 512 (issue: clusters).

Runs the product's path (``prepare`` / ``run_frames`` of ``scenes/default.toml`` at
``--levels`` subdivision levels, one frame, one thread per rank) under ``mpiexec -n p`` for
each ``--ranks`` (ranks beyond the cores are oversubscribed: their times are not scaling
data, their counts are). Each run records per rank: the frame's shell time and its split
(evaluation, set-up, CG), the owned and halo vertices of the fine level, and per frame the
counts that carry the messages: distributed operator products (one halo exchange each),
CG iterations (about three global reductions each), Newton set-ups (parallel Galerkin
products) and energy evaluations (each allgathers the 3n gradient or reduces a value).

The model (latency-bandwidth, Hockney): a frame on p ranks takes

    T(p) = T_c b(p) / p + X (alpha + 24 h(p) / beta) + R alpha log2 p
           + E (alpha log2 p + 24 n (p - 1) / (p beta))

with ``T_c`` the measured 1-rank compute, ``b(p)`` the largest share over the mean share
(balanced bisection of the clusters), ``X`` products, ``R`` reductions, ``E`` allgathers per
frame (measured counts), ``h(p)`` the halo vertices of a rank (fitted ``h = c sqrt(n / p)``,
a surface split into compact parts), 24 bytes per vertex (3 doubles), alpha and beta a
typical cluster network (defaults: 2 us, 10 GB/s, InfiniBand EDR). Checked against the
measured multi-rank frames (with this machine's shared memory, 0.5 us and 5 GB/s), the
difference per product is the implementation's own overhead (synchronisation, per-call
costs); the predictions for p = 1 .. 512, for this shell and for ``--predict-vertices``
(compute scaled as n^1.12, ``benchmarks/scaling.py``; counts kept), are given without it
("ideal") and with it ("as built"); the speed-up column is the as-built one.

Usage::

    python benchmarks/split_scaling.py --levels 4 --ranks 1 2 3 4
    python benchmarks/split_scaling.py --levels 2 --ranks 1 2 --out /tmp/s.json   # quick

Writes ``benchmarks/results/split_scaling.json`` (``--out``); prints the measured and the
modelled tables.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from wrinkles.launch import python_on_ranks

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "split_scaling.json"
SCENE = REPO / "scenes" / "default.toml"
COMPUTE_EXPONENT = 1.12
"""Frame compute ~ n^1.12 (multigrid-CG, 10k to 1.26M vertices: benchmarks/scaling.py)."""


def worker(levels: int, out: Path) -> None:
    """One frame through prepare/run_frames on COMM_WORLD; rank 0 writes the JSON record."""
    from models.backend import MPI
    from solvers import multigrid
    from solvers.decomposition import split_newton
    from wrinkles.runner import prepare, run_frames
    from wrinkles.scene import load_scene

    counts = {"products": 0, "evaluations": 0, "values": 0}

    def counted(cls: Any, name: str, key: str) -> None:
        original = getattr(cls, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            counts[key] += 1
            return original(*args, **kwargs)

        setattr(cls, name, wrapper)

    counted(multigrid.LowRankOperator, "mult", "products")
    counted(split_newton.SplitShellEnergy, "evaluate", "evaluations")
    counted(split_newton.SplitShellEnergy, "value", "values")
    comm = MPI.COMM_WORLD
    scene = load_scene(SCENE, [f"shell.subdivision.levels={levels}", "output.render=false",
                               "output.xdmf=false", "time.frames=1", "shell.solver.threads=1"])
    run = prepare(scene, out / "run", comm, overwrite=True, log=lambda line: None)
    run_frames(run, log=lambda line: None)
    record, shell = run.records[-1], run.shell
    assert shell is not None  # the default scene has a shell
    d = record.details
    mine: dict[str, Any] = {"shell_time": record.stage_times.get("shell", 0.0),
                            "evaluate": d["shell_time_evaluate"],
                            "setup": d["shell_time_factorize"], "solve": d["shell_time_solve"]}
    solver = shell.solver
    if isinstance(solver, split_newton.SplitNewtonSolver):
        patch = solver.energy.patch
        mine.update(owned=int(patch.interior.size),
                    halo=int(patch.local.size - patch.interior.size))
        stats = getattr(solver.linear, "stats", None)  # the direct solve has none
    else:
        mine.update(owned=int(shell.rest.shape[0]), halo=0)
        stats = solver.krylov.stats if solver.krylov is not None else None
    mine.update(cg_iterations=int(sum(stats.iterations)) if stats else 0,
                setups=int(stats.setups) if stats else 0, **counts)
    ranks = comm.gather(mine, root=0)
    if comm.rank == 0:
        doc = {"ranks": comm.size, "vertices": int(shell.rest.shape[0]),
               "newton_iterations": d["shell_iterations"], "per_rank": ranks}
        (out / "record.json").write_text(json.dumps(doc))


def worker_parser(doc: str, results: Path) -> argparse.ArgumentParser:
    """Arguments of a benchmark measured by :func:`run_worker`: levels, ranks, out, worker."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--levels", type=int, default=4)
    p.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    p.add_argument("--timeout", type=float, default=3600.0)
    p.add_argument("--out", type=Path, default=results)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    return p


def run_worker(script: str, levels: int, ranks: int, timeout: float,
               petsc_options: str = "") -> dict[str, Any]:
    """Run ``script --worker --levels L --out DIR`` under ``mpiexec -n ranks``; its record.

    The worker writes ``DIR/record.json`` on rank 0. ``petsc_options`` are added to
    ``PETSC_OPTIONS`` (``{out}`` in them names the run's temporary directory).
    """
    name = Path(script).stem
    with tempfile.TemporaryDirectory(prefix=f"{name}_") as tmp:
        cmd = [*python_on_ranks(ranks), script, "--worker", "--levels", str(levels),
               "--out", tmp]
        # one BLAS thread per process, as the CLI has (wrinkles/__init__.py): this script
        # loads numpy before the package could cap it
        env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", **os.environ}
        if petsc_options:
            extra = petsc_options.format(out=tmp)
            env["PETSC_OPTIONS"] = f"{env.get('PETSC_OPTIONS', '')} {extra}".strip()
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                              cwd=REPO, env=env)
        if proc.returncode != 0:
            raise SystemExit(f"{name}: {ranks} rank(s) failed:\n{proc.stderr[-3000:]}")
        return json.loads((Path(tmp) / "record.json").read_text())


def halo_fit(runs: list[dict[str, Any]]) -> float:
    """``c`` of ``h = c sqrt(n / p)`` fitted (least squares) to the measured largest halos."""
    pts = [(math.sqrt(r["vertices"] / r["ranks"]), max(x["halo"] for x in r["per_rank"]))
           for r in runs if r["ranks"] > 1]
    if not pts:
        return 0.0
    x, y = np.array(pts).T
    return float(x @ y / (x @ x))


def model(n: int, p: int, compute: float, counts: dict[str, float], c_halo: float,
          alpha: float, beta: float, balance: float = 1.0,
          overhead: float = 0.0) -> dict[str, float]:
    """Modelled frame time on p ranks and its parts (module docstring) [s].

    ``overhead``: seconds per distributed product beyond the network's (synchronisation and
    per-call costs of the implementation; calibrated on a measured run, 0 = the ideal).
    """
    halo = c_halo * math.sqrt(n / p) if p > 1 else 0.0
    log_p = math.log2(p) if p > 1 else 0.0
    parts = {
        "compute": compute * balance / p,
        "halo": (counts["products"] * (alpha + overhead + 24.0 * halo / beta)
                 if p > 1 else 0.0),
        "reductions": counts["reductions"] * alpha * log_p,
        "allgathers": counts["gathers"] * (alpha * log_p + 24.0 * n * (p - 1) / (p * beta)),
    }
    parts["total"] = sum(parts.values())
    return parts


def counts_of(run: dict[str, Any]) -> dict[str, float]:
    """Messages per frame of a multi-rank run: products, reductions, allgathers (rank 0)."""
    r0 = run["per_rank"][0]
    return {"products": float(r0["products"]),
            "reductions": 3.0 * r0["cg_iterations"] + float(r0["values"] + r0["evaluations"]),
            "gathers": 2.0 * r0["evaluations"]}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Measure, fit, predict; print both tables; write the JSON."""
    p = worker_parser(__doc__, RESULTS)
    p.add_argument("--alpha", type=float, default=2e-6, help="network latency [s]")
    p.add_argument("--beta", type=float, default=10e9, help="network bandwidth [B/s]")
    p.add_argument("--predict-vertices", type=int, default=1_000_000)
    args = p.parse_args(argv)
    if args.worker:
        worker(args.levels, args.out)
        return {}
    if 1 not in args.ranks or not any(r > 1 for r in args.ranks):
        raise SystemExit("split_scaling: --ranks needs 1 and at least one count above 1")
    cores = os.cpu_count() or 1
    runs = [run_worker(__file__, args.levels, r, args.timeout)
            for r in sorted(set(args.ranks))]
    print(f"{'ranks':>5} {'vertices':>9} {'newton':>6} {'shell s':>8} {'eval':>6} "
          f"{'setup':>6} {'CG':>6} {'owned max':>9} {'halo max':>8} {'products':>8} "
          f"{'CG its':>6}")
    for r in runs:
        rows = r["per_rank"]
        worst = max(rows, key=lambda x: x["shell_time"])
        print(f"{r['ranks']:>5} {r['vertices']:>9} {r['newton_iterations']:>6} "
              f"{worst['shell_time']:8.2f} {worst['evaluate']:6.2f} {worst['setup']:6.2f} "
              f"{worst['solve']:6.2f} {max(x['owned'] for x in rows):>9} "
              f"{max(x['halo'] for x in rows):>8} {rows[0]['products']:>8} "
              f"{rows[0]['cg_iterations']:>6}" + ("  (oversubscribed)" if r["ranks"] > cores
                                                  else ""))
    serial = runs[0]
    n, compute = serial["vertices"], serial["per_rank"][0]["shell_time"]
    multi = [r for r in runs if r["ranks"] > 1]
    counts, c_halo = counts_of(multi[0]), halo_fit(multi)
    check = [r for r in multi if r["ranks"] <= cores]
    doc: dict[str, Any] = {"levels": args.levels, "alpha": args.alpha, "beta": args.beta,
                           "compute_exponent": COMPUTE_EXPONENT,
                           "runs": runs, "counts": counts, "halo_coefficient": c_halo,
                           "check": [], "predictions": []}
    print(f"\nmodel: alpha {args.alpha:g} s, beta {args.beta:g} B/s, halo {c_halo:.2f} "
          f"sqrt(n/p), per frame {counts['products']:.0f} products, "
          f"{counts['reductions']:.0f} reductions, {counts['gathers']:.0f} allgathers")
    overhead = 0.0
    for r in check:
        rows = r["per_rank"]
        balance = max(x["owned"] for x in rows) * r["ranks"] / n
        local = model(n, r["ranks"], compute, counts, c_halo, 0.5e-6, 5e9, balance)
        measured = max(x["shell_time"] for x in rows)
        overhead = max(0.0, (measured - local["total"]) / max(counts["products"], 1.0))
        doc["check"].append({"ranks": r["ranks"], "measured": measured,
                             "model_shared_memory": local["total"],
                             "overhead_per_product": overhead})
        print(f"check at {r['ranks']} ranks (this machine: alpha 0.5 us, beta 5 GB/s): "
              f"measured {measured:.2f} s, network model {local['total']:.2f} s: "
              f"{overhead * 1e6:.0f} us per product beyond the network")
    doc["overhead_per_product"] = overhead
    print(f"\n{'vertices':>9} {'ranks':>5} {'ideal s':>8} {'as built':>8} {'compute':>8} "
          f"{'halo':>7} {'reduce':>7} {'gather':>7} {'speed-up':>8}")
    for size in (n, args.predict_vertices):
        work = compute * (size / n) ** COMPUTE_EXPONENT
        for ranks in (1, 2, 4, 16, 64, 512):
            m = model(size, ranks, work, counts, c_halo, args.alpha, args.beta)
            built = model(size, ranks, work, counts, c_halo, args.alpha, args.beta,
                          overhead=overhead)["total"]
            doc["predictions"].append({"vertices": size, "ranks": ranks, **m,
                                       "as_built": built})
            print(f"{size:>9} {ranks:>5} {m['total']:8.3f} {built:8.3f} {m['compute']:8.3f} "
                  f"{m['halo']:7.3f} {m['reductions']:7.3f} {m['allgathers']:7.3f} "
                  f"{work / built:8.1f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    return doc


if __name__ == "__main__":
    main()
