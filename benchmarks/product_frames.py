"""Frames of ``wrinkles run`` as a user runs them: this tree against an earlier commit, one run.

For each scene the command ``wrinkles run SCENE --out TMP --overwrite --set output.render=false
[--frames N] [--set ...]`` is run in a subprocess, once with this tree and, with ``--before
REV``, once with a detached git worktree of ``REV`` (its packages first on ``PYTHONPATH``, the
same interpreter and venv), alternating per scene so both see the same machine load; each code
first runs two frames (one with ``--frames 1``) of every scene on every rank count, outside
the table, so that the numba kernels the scene uses (the split solver's on ranks; the serial
shell's where two ranks overlap the stages, which one frame does not) are compiled into that
tree's cache before it is timed (a scene whose kernels the warm-up missed pays their
compilation inside its frames: 8-10 s on the default scene, 4.9 s on the demo's overlapped
frames). From each run's ``summary.json`` the table reports
per scene and code:

* frames, body Newton iterations (``body``), shell Newton iterations, factorisations
  (numeric, shifted retries included) and the failed ones (attempts beyond one per
  iteration that factorised), shell set-up method and
  threads when the code records them;
* the frames' time: process CPU time of the frames (``cpu_time`` of each frame record; for
  code that does not record it and for runs on several ranks, the frames' wall time, marked
  ``*``: a serial, one-thread run on an idle core has CPU = wall, rank 0's CPU leaves out the
  other ranks' work) and wall time, and seconds per frame;
* the whole command's wall time (``cmd s``: from its start to its exit, the ranks' launch,
  imports, set-up and output included, what a user waits for) and the process's total user +
  system CPU (``resource.getrusage`` of the child: set-up, JIT and output included);
* the final shell energy, the most self-intersecting face pairs of any frame (``x-pairs``,
  ``-`` for code that does not count them) and the frames whose shell solve did not
  converge;
* with ``--seeds N``: each scene run N times, with ``shell.imperfection_seed`` 0 (the key not
  passed, so earlier code runs it too) to N - 1 (a scene without a ``[shell]`` table runs N
  times as it is); a wrinkle pattern is one of many nearly equal minima and the seed picks
  it, so a change is judged against the spread over the seeds (a table of mean, min and max
  per scene and code follows the rows);
* with ``--ranks 1 2``: each run under ``mpiexec -n N`` (the venv's), every rank count of a
  scene side by side; the frames' wall time is then the measure (the frames' CPU is rank 0's),
  with the speed-up against the first rank count of the same code and the peak resident
  memory of the largest rank (``peak_memory_mb`` of the summary, when the code records it);
  a serial command that the code itself runs on the cores as ranks (a large one-way shell,
  :func:`solvers.solver_choice.choose_ranks`) shows the ranks its summary records in ``np``
  and is measured by its wall time, as any run on ranks.

Writes ``benchmarks/results/product_frames.json`` (``--out``). Timings on a shared machine are
contended; the load average is recorded before and after every run.

Usage::

    python benchmarks/product_frames.py --before 17b4608
    python benchmarks/product_frames.py --scenes default ball_sofa_coarse --before HEAD~1
    python benchmarks/product_frames.py --scenes default --frames 1 \\
        --set shell.subdivision.levels=4 --before 17b4608
    python benchmarks/product_frames.py --scenes default ball_sofa_coarse --ranks 1 2 \\
        --set shell.solver.threads=1 --before HEAD~1
    python benchmarks/product_frames.py --scenes default twisted_cylinder --seeds 6 \\
        --before HEAD~1
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from wrinkles.config import read_toml
from wrinkles.launch import python_on_ranks

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "product_frames.json"
SCENES: tuple[str, ...] = ("default", "ball_sofa_coarse")


def scene_path(name: str) -> Path:
    """``scenes/<name>.toml`` of this repository, or ``name`` itself when it is a file."""
    path = Path(name)
    return path if path.suffix == ".toml" else REPO / "scenes" / f"{name}.toml"


def has_shell(scene: Path) -> bool:
    """Whether the scene file has a ``[shell]`` table (the seeds vary its imperfection)."""
    return "shell" in read_toml(scene)


def worktree(rev: str, where: Path) -> Path:
    """Check out ``rev`` into a detached worktree under ``where``; return its path.

    Raises:
        SystemExit: ``rev`` names no commit of this repository (exit 1, the message names it).
    """
    known = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet",
                            f"{rev}^{{commit}}"], check=False, capture_output=True, text=True)
    if known.returncode:
        raise SystemExit(f"--before {rev}: no such commit in {REPO}")
    path = where / f"before-{rev.replace('/', '_')}"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "--force", str(path),
                    rev], check=True, capture_output=True, text=True)
    return path


def drop_worktree(path: Path) -> None:
    """Remove a worktree made by :func:`worktree`."""
    subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(path)],
                   check=False, capture_output=True)


def run_cli(code: Path, scene: Path, out: Path, frames: int | None,
            overrides: list[str], timeout: float, ranks: int = 1) -> dict[str, Any]:
    """Run the CLI of the tree ``code`` on ``scene`` (on ``ranks`` MPI ranks); its row."""
    cmd = [*python_on_ranks(ranks), "-m", "wrinkles", "run", str(scene), "--out", str(out),
           "--overwrite", "--set", "output.render=false"]
    cmd += ["--frames", str(frames)] if frames else []
    for item in overrides:
        cmd += ["--set", item]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(code), os.environ.get(
        "PYTHONPATH", "")]).rstrip(os.pathsep))
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True,
                          timeout=timeout)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    row: dict[str, Any] = {
        "exit": proc.returncode, "process_wall": wall,
        "process_cpu": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "load_before": load, "load_after": os.getloadavg()[0]}
    if proc.returncode != 0:
        row["error"] = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return row
    return row | summary_row(json.loads((out / "summary.json").read_text()))


def summary_row(summary: dict[str, Any]) -> dict[str, Any]:
    """Frames, iterations, factorisations and times of one run's ``summary.json``."""
    frames = summary["frames"]
    details = [f.get("details", {}) for f in frames]
    its = [int(d.get("shell_iterations", 0)) for d in details]
    facts = [int(d.get("shell_factorizations", 0)) for d in details]
    has_cpu = all("cpu_time" in f for f in frames)
    solver = summary.get("run", {}).get("shell", {}).get("solver", {})
    return {
        "frames": len(frames), "shell_iterations": its, "factorizations": facts,
        "body_iterations": [int(f.get("newton_iterations", 0)) for f in frames],
        "failed_factorizations": [max(0, n - i) for n, i in zip(facts, its, strict=True)],
        "frames_cpu": sum(f["cpu_time"] for f in frames) if has_cpu else None,
        "frames_wall": sum(f["wall_time"] for f in frames),
        "shell_energy": [d.get("shell_energy") for d in details],
        "unconverged": [f["frame"] for f, d in zip(frames, details, strict=True)
                        if d.get("shell_converged") is False],
        "self_intersections": [d.get("shell_self_intersections") for d in details],
        "method": solver.get("method", "direct"), "threads": solver.get("threads", 1),
        "run_ranks": int(summary.get("run", {}).get("ranks", 1)),
        "peak_memory_mb": max(summary.get("run", {}).get("peak_memory_mb") or [0.0]) or None}


def print_row(scene: str, label: str, r: dict[str, Any]) -> None:
    """One line of the table."""
    if r["exit"] != 0:
        print(f"{scene:>18} {label:>8} {r['ranks']:>2}  FAILED (exit {r['exit']}): "
              f"{' '.join(r['error'])}")
        return
    n = max(r["frames"], 1)
    cpu = r["frames_cpu"]
    ranks = r.get("run_ranks", r["ranks"])
    shown, mark = (cpu, " ") if cpu is not None and ranks == 1 else (r["frames_wall"], "*")
    failed, total = sum(r["failed_factorizations"]), sum(r["factorizations"])
    speedup = f"{r['speedup']:5.2f}x" if r.get("speedup") else f"{'-':>6}"
    memory = f"{r['peak_memory_mb']:7.0f}" if r.get("peak_memory_mb") else f"{'-':>7}"
    print(f"{scene:>18} {label:>8} {ranks:>2} {r['method']:>9} {r['threads']:>3} "
          f"{r['frames']:>3} {sum(r['body_iterations']):>6} {sum(r['shell_iterations']):>6} "
          f"{total:>6} {failed:>6} "
          f"{shown:9.2f}{mark} {shown / n:8.2f} {r['frames_wall']:8.2f} {speedup} {memory} "
          f"{r['process_wall']:7.2f} {r['process_cpu']:8.2f} "
          f"{_last_energy(r['shell_energy']):12.6e} "
          f"{_most_pairs(r.get('self_intersections')):>7} {r['unconverged'] or ''}", flush=True)


def _most_pairs(values: list[int | None] | None) -> str:
    """The most self-intersecting face pairs of any frame; "-" where the code counts none."""
    counted = [v for v in values or [] if v is not None]
    return str(max(counted)) if counted else "-"


def _last_energy(values: list[float | None] | None) -> float:
    """The last frame's shell energy, NaN for a scene without a shell."""
    last = values[-1] if values else None
    return float(last) if last is not None else float("nan")


HEADER = (f"{'scene':>18} {'code':>8} {'np':>2} {'method':>9} {'thr':>3} {'frm':>3} "
          f"{'body':>6} {'its':>6} {'facts':>6} {'failed':>6} {'frames s':>10} {'s/frame':>8} "
          f"{'wall s':>8} {'speed':>6} {'mem MB':>7} {'cmd s':>7} {'proc CPU':>8} "
          f"{'final W':>12} "
          f"{'x-pairs':>7} unconverged")


def spread_table(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Print and return mean, min and max over the seeds per scene, code and rank count.

    Shell iterations and failed factorisations of all frames, the frames' time (CPU of a serial
    run, wall where the code does not record CPU or the run has several ranks: rank 0's CPU
    leaves out the others' work and its own waits) and the final shell energy; runs that failed
    are counted apart.
    """
    print(f"\nspread over the seeds (mean [min - max]):\n{'scene':>18} {'code':>8} {'np':>2} "
          f"{'runs':>4} {'shell its':>18} {'failed %':>9} {'frames s':>20} {'final W':>36}")
    table = []
    keys = dict.fromkeys((r["scene"], r["code"], r["ranks"]) for r in rows)
    for scene, code, asked in keys:
        runs = [r for r in rows if (r["scene"], r["code"], r["ranks"]) == (scene, code, asked)]
        ranks = max(r.get("run_ranks", asked) for r in runs)
        ok = [r for r in runs if r["exit"] == 0]
        if not ok:
            continue
        its = [sum(r["shell_iterations"]) for r in ok]
        failed = [100.0 * sum(r["failed_factorizations"]) / max(sum(r["factorizations"]), 1)
                  for r in ok]
        times = [r["frames_cpu"] if r["frames_cpu"] is not None and ranks == 1
                 else r["frames_wall"] for r in ok]
        energy = [_last_energy(r["shell_energy"]) for r in ok]
        entry = {"scene": scene, "code": code, "ranks": ranks, "runs": len(ok),
                 "failed_runs": len(runs) - len(ok),
                 "shell_iterations": _stats(its), "failed_percent": _stats(failed),
                 "frames_time": _stats(times), "final_energy": _stats(energy)}
        table.append(entry)
        print(f"{scene:>18} {code:>8} {ranks:>2} {len(ok):>4} "
              f"{_shown(entry['shell_iterations'], '.0f'):>18} "
              f"{entry['failed_percent']['mean']:9.1f} {_shown(entry['frames_time'], '.2f'):>20} "
              f"{_shown(entry['final_energy'], '.6g'):>36}", flush=True)
    return table


def _stats(values: list[float]) -> dict[str, float | None]:
    """Mean, population standard deviation, min and max; None where a value is NaN (no shell)."""
    if any(v != v for v in values):
        return {"mean": None, "sd": None, "min": None, "max": None}
    return {"mean": statistics.fmean(values), "sd": statistics.pstdev(values),
            "min": min(values), "max": max(values)}


def _shown(stats: dict[str, float | None], fmt: str) -> str:
    """``mean [min - max]``, or ``-`` without values."""
    if stats["mean"] is None:
        return "-"
    return f"{stats['mean']:{fmt}} [{stats['min']:{fmt}} - {stats['max']:{fmt}}]"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES),
                   help="scene names under scenes/ or .toml paths")
    p.add_argument("--before", default=None, help="git revision to compare with")
    p.add_argument("--frames", type=int, default=None, help="frames per run (scene's own)")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="scene override for both codes (repeatable)")
    p.add_argument("--ranks", type=int, nargs="+", default=[1],
                   help="MPI rank counts to run each scene on (mpiexec -n N for N > 1)")
    p.add_argument("--seeds", type=int, default=1,
                   help="runs per scene with shell.imperfection_seed 0 .. N-1 (spread table)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    p.add_argument("--out", type=Path, default=RESULTS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the table; return (and write) the JSON document."""
    args = parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="product_frames_"))
    codes: list[tuple[str, Path]] = [("this", REPO)]
    if args.before:
        codes.append((args.before, worktree(args.before, tmp)))
    doc: dict[str, Any] = {"machine": platform.node(), "cores": os.cpu_count(),
                           "before": args.before, "frames": args.frames,
                           "overrides": args.overrides, "ranks": args.ranks, "rows": []}
    warm_frames = 1 if args.frames == 1 else 2  # a timed single frame needs no second
    print(HEADER)
    try:
        for (label, code), scene, ranks in itertools.product(codes, args.scenes, args.ranks):
            warm = run_cli(code, scene_path(scene), tmp / "out", warm_frames, args.overrides,
                           args.timeout, ranks)  # numba compiles the kernels into its cache
            print(f"{'(warm-up)':>18} {label:>8}  {warm_frames} frame(s) of {scene} on {ranks} "
                  f"rank(s): exit {warm['exit']}, {warm['process_wall']:.1f} s", flush=True)
        for scene, seed in itertools.product(args.scenes, range(args.seeds)):
            seeded = args.overrides + ([f"shell.imperfection_seed={seed}"]
                                       if seed and has_shell(scene_path(scene)) else [])
            first: dict[str, float] = {}  # frames' wall time at the first rank count, per code
            for ranks in args.ranks:
                for label, code in codes:
                    row = run_cli(code, scene_path(scene), tmp / "out", args.frames,
                                  seeded, args.timeout, ranks)
                    row.update(scene=scene, code=label, ranks=ranks, seed=seed)
                    if row["exit"] == 0:
                        first.setdefault(label, row["frames_wall"])
                        row["speedup"] = first[label] / row["frames_wall"]
                    doc["rows"].append(row)
                    print_row(scene, label, row)
                    args.out.parent.mkdir(parents=True, exist_ok=True)
                    args.out.write_text(json.dumps(doc, indent=1))
        if args.seeds > 1:
            doc["spread"] = spread_table(doc["rows"])
            args.out.write_text(json.dumps(doc, indent=1))
    finally:
        for _label, code in codes[1:]:
            drop_worktree(code)
        shutil.rmtree(tmp, ignore_errors=True)
    return doc


if __name__ == "__main__":
    main()
