"""A one-way scene's frames with body and shell stages overlapped over two processes.

``mpiexec -n N wrinkles run`` splits the body and the shell over all ranks, stage after stage.
In a one-way scene the body's frame ``k + 1`` does not depend on the shell's frame ``k``, so
two processes can overlap the stages instead: rank 0 steps the body (and its balls) frame
after frame and sends the body's displacement ``u`` and time ``t`` of each frame
(``MPI.Isend``); rank 1 sets them into its copy of the body and runs the shell stage alone.
Each process builds the scene's serial run (:func:`wrinkles.runner.prepare` on
``COMM_SELF``), so the stages are the serial ones and the final shell energy must be the
serial run's bit for bit. The frame time of the overlap is bounded below by the slower
stage, ``max(body, shell)``, against ``body + shell`` in series.

This measures that layout, which the product does not take (docs/notes/distributed-shell.md):
per scene and repeat, the serial frames (one process) and the overlapped frames (two
processes under the venv's ``mpiexec``), alternating so both see the same machine load; the
wall time runs from a barrier after the set-up to the last shell frame (XDMF and render
off). Writes ``benchmarks/results/overlap_stages.json`` (``--out``).

Usage::

    python benchmarks/overlap_stages.py
    python benchmarks/overlap_stages.py --scenes ball_sofa_coarse bunny_drop --repeat 2
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.product_frames import mpiexec, scene_path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "overlap_stages.json"
SCENES: tuple[str, ...] = ("ball_sofa_coarse",)
OVERRIDES: tuple[str, ...] = ("output.render=false", "output.xdmf=false")


def worker(scene_file: str, overrides: list[str], out: Path) -> dict[str, Any]:
    """Run the scene's frames in series (one process) or overlapped (two); rank 0's result.

    Returns ``{"processes", "frames", "wall", "shell_energy"}`` on rank 0 (the overlapped run's
    energy comes from rank 1), ``{}`` on rank 1.

    Raises:
        SystemExit: a scene without a one-way shell (its stages are not body then shell), or
            more than two processes.

    """
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # before the backend loads BLAS and MUMPS
    import numpy as np

    from models.backend import MPI
    from wrinkles.runner import prepare, run_frame
    from wrinkles.scene import load_scene

    world = MPI.COMM_WORLD
    if world.size > 2:
        raise SystemExit("overlap_stages: one or two processes")
    scene = load_scene(scene_file, [*OVERRIDES, *overrides])
    run = prepare(scene, out / f"rank{world.rank}", MPI.COMM_SELF, overwrite=True)
    if [name for name, _ in run.stages][1:] != ["shell"]:
        raise SystemExit(f"overlap_stages: {scene_file} has no one-way shell stage")
    world.Barrier()
    start = time.perf_counter()
    energy = 0.0
    if world.size == 1:
        for frame in range(1, run.n_frames + 1):
            energy = run_frame(run, frame).details["shell_energy"]
    elif world.rank == 0:
        sent: list[np.ndarray] = []  # kept alive until every send completed
        requests = []
        for frame in range(1, run.n_frames + 1):
            run.stages[0][1](frame)
            sent.append(np.append(run.body.u.x.array, run.body.t))
            requests.append(world.Isend(sent[-1], dest=1, tag=frame))
        MPI.Request.Waitall(requests)
    else:
        n = run.body.u.x.array.size
        for frame in range(1, run.n_frames + 1):
            received = np.empty(n + 1)
            world.Recv(received, source=0, tag=frame)
            run.body.u.x.array[:], run.body.t = received[:n], float(received[n])
            energy = run.stages[1][1](frame)["shell_energy"]
    energy = world.bcast(energy, root=world.size - 1)
    world.Barrier()
    wall = time.perf_counter() - start
    if world.rank:
        return {}
    return {"processes": world.size, "frames": run.n_frames, "wall": wall,
            "shell_energy": energy}


def measure(scene: Path, overrides: list[str], processes: int, out: Path,
            timeout: float) -> dict[str, Any]:
    """Run :func:`worker` in a subprocess on ``processes`` processes; its result."""
    launch = [mpiexec(), "-n", "2"] if processes == 2 else []
    cmd = [*launch, sys.executable, str(Path(__file__).resolve()), "--worker", str(scene),
           "--worker-out", str(out), *(f"--set={item}" for item in overrides)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return {"processes": processes, "exit": proc.returncode, "error": tail}
    return {"exit": 0, **json.loads(lines[-1])}


def compare(scene: Path, repeat: int, overrides: list[str], tmp: Path,
            timeout: float) -> dict[str, Any]:
    """One serial and one overlapped run of ``scene``; the row, printed."""
    serial, overlap = (measure(scene, overrides, p, tmp / f"{scene.stem}_{p}", timeout)
                       for p in (1, 2))
    row: dict[str, Any] = {"scene": scene.stem, "repeat": repeat, "serial": serial,
                           "overlapped": overlap}
    if serial["exit"] == 0 and overlap["exit"] == 0:
        row["speedup"] = serial["wall"] / overlap["wall"]
        row["same_energy"] = serial["shell_energy"] == overlap["shell_energy"]
        print(f"{scene.stem:>18} {repeat:>6} {serial['wall']:>9.3f} {overlap['wall']:>9.3f} "
              f"{row['speedup']:>5.2f}x {row['same_energy']}", flush=True)
    else:
        print(f"{scene.stem:>18} {repeat:>6} failed: {serial.get('error')} "
              f"{overlap.get('error')}", flush=True)
    return row


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Parse ``argv``, measure every scene in series and overlapped, print and write the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--worker-out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        result = worker(args.worker, args.set, args.worker_out)
        if result:
            print(json.dumps(result), flush=True)
        return result
    rows = []
    print(f"{'scene':>18} {'repeat':>6} {'serial s':>9} {'overlap s':>9} {'speed':>6} same W")
    with tempfile.TemporaryDirectory(prefix="overlap_stages_") as tmp:
        for name in args.scenes:
            scene = scene_path(name)
            for k in range(args.repeat):
                rows.append(compare(scene, k, args.set, Path(tmp), args.timeout))
    speedups = [r["speedup"] for r in rows if "speedup" in r]
    doc = {"rows": rows, "overrides": args.set, "median_speedup":
           statistics.median(speedups) if speedups else None}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.out}")
    return doc


if __name__ == "__main__":
    main()
