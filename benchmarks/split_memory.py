"""Memory of the shell per rank: one frame of the product on 1 and on N ranks (issue: clusters).

Runs the product's path (``prepare`` / ``run_frames`` of ``scenes/default.toml`` at
``--levels`` subdivision levels, one frame, one thread per rank) under ``mpiexec -n p`` for
each ``--ranks`` and records per rank:

* ``rss_before_shell``: resident set when the shell starts to be built (imports, the body);
* ``rss_peak``: the process's peak resident set (``ru_maxrss``); their difference is the
  *shell's peak* (everything the shell stage adds: its arrays, PETSc objects, compiled
  kernels, allocator slack), the issue's measure;
* ``python_peak``: peak of the Python heap, numpy arrays included (``tracemalloc``);
* ``petsc_peak``: peak of PETSc's allocations (``PetscMallocGetMaximumUsage`` with PETSc's
  allocation log on); the two are the shell's *data* (less the body's small share).

``tracemalloc`` slows the frame: the times are not speed data (``product_frames.py`` is).

Usage::

    python benchmarks/split_memory.py --levels 4 --ranks 1 2
    python benchmarks/split_memory.py --levels 2 --ranks 1 2 --out /tmp/m.json   # quick

Writes ``benchmarks/results/split_memory.json`` (``--out``) and prints the table with the
ratio of every rank count's largest shell peak to the 1-rank one.
"""

from __future__ import annotations

import ctypes
import json
import resource
from pathlib import Path
from typing import Any

from benchmarks.shell_solve import proc_status_mib
from benchmarks.split_scaling import run_worker, worker_parser

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "split_memory.json"
SCENE = REPO / "scenes" / "default.toml"
MB = 2.0**20


def _petsc_peak_mb() -> float:
    """``PetscMallocGetMaximumUsage`` of the loaded PETSc library [MB]."""
    with open("/proc/self/maps") as maps:
        paths = {line.split()[-1] for line in maps if "libpetsc.so" in line}
    lib = ctypes.CDLL(sorted(paths)[0])
    value = ctypes.c_double()
    lib.PetscMallocGetMaximumUsage(ctypes.byref(value))
    return value.value / MB


def worker(levels: int, out: Path) -> None:
    """One frame through prepare/run_frames on COMM_WORLD; rank 0 writes the JSON record."""
    import tracemalloc

    from models.backend import MPI
    from wrinkles import runner
    from wrinkles.scene import load_scene

    comm = MPI.COMM_WORLD
    marks: dict[str, float] = {}
    build = runner.build_shell

    def measured_build(*args: Any, **kwargs: Any) -> Any:
        marks["rss_before_shell"] = proc_status_mib("VmRSS")
        tracemalloc.start()
        return build(*args, **kwargs)

    runner.build_shell = measured_build
    scene = load_scene(SCENE, [f"shell.subdivision.levels={levels}", "output.render=false",
                               "output.xdmf=false", "time.frames=1", "shell.solver.threads=1"])
    run = runner.prepare(scene, out / "run", comm, overwrite=True, log=lambda line: None)
    runner.run_frames(run, log=lambda line: None)
    mine = dict(marks, rss_peak=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                python_peak=tracemalloc.get_traced_memory()[1] / MB,
                petsc_peak=_petsc_peak_mb())
    mine["shell_peak"] = mine["rss_peak"] - mine["rss_before_shell"]
    ranks = comm.gather(mine, root=0)
    if comm.rank == 0:
        assert run.shell is not None  # the default scene has a shell
        doc = {"ranks": comm.size, "vertices": int(run.shell.rest.shape[0]), "per_rank": ranks}
        (out / "record.json").write_text(json.dumps(doc))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Measure every rank count; print the table; write the JSON."""
    args = worker_parser(__doc__, RESULTS).parse_args(argv)
    if args.worker:
        worker(args.levels, args.out)
        return {}
    if 1 not in args.ranks:
        raise SystemExit("split_memory: --ranks needs 1 (the serial reference)")
    # PETSc's allocation log on (its report at exit goes to a file, none of it needed)
    log = "-malloc_view {out}/malloc_view -malloc_view_threshold 1e15"
    runs = [run_worker(__file__, args.levels, r, args.timeout, log)
            for r in sorted(set(args.ranks))]
    keys = ("rss_before_shell", "rss_peak", "shell_peak", "python_peak", "petsc_peak")
    serial = runs[0]["per_rank"][0]
    print(f"{'ranks':>5} {'vertices':>9} {'rank':>4} " + " ".join(f"{k:>16}" for k in keys)
          + f" {'shell / 1 rank':>14} {'data / 1 rank':>13}")
    data_1 = serial["python_peak"] + serial["petsc_peak"]
    for run in runs:
        for rank, row in enumerate(run["per_rank"]):
            data = row["python_peak"] + row["petsc_peak"]
            print(f"{run['ranks']:>5} {run['vertices']:>9} {rank:>4} "
                  + " ".join(f"{row[k]:16.1f}" for k in keys)
                  + f" {row['shell_peak'] / serial['shell_peak']:14.2f} {data / data_1:13.2f}")
    doc = {"levels": args.levels, "scene": SCENE.name, "runs": runs,
           "ratios": {str(run["ranks"]): {
               "shell_peak": max(r["shell_peak"] for r in run["per_rank"])
               / serial["shell_peak"],
               "data_peak": max(r["python_peak"] + r["petsc_peak"] for r in run["per_rank"])
               / data_1} for run in runs}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2))
    print(f"wrote {args.out}")
    return doc


if __name__ == "__main__":
    main()
