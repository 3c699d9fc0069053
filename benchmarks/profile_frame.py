"""Profile the frame loop of ``wrinkles run`` (cProfile) and report per-frame wall times.

Runs a scene (default ``scenes/default.toml``) for ``--frames`` frames in a temporary output
directory, serially, with rendering off (rendering runs once after the loop, it is not part of
a frame), under ``cProfile``. Writes the top ``--top`` functions by cumulative time, preceded
by the per-frame wall times and stage times from the run records, to
``benchmarks/results/profile_<label>.txt`` (``--label before`` / ``after``) and the frame
times to ``benchmarks/results/profile_<label>.json``.

Usage::

    python benchmarks/profile_frame.py --label before --frames 3
    python benchmarks/profile_frame.py --label after --frames 3 --set shell.subdivision.levels=1

``--series N FRAMES`` instead times the shell XDMF series alone (no solve): ``FRAMES`` steps
of an ``N``-vertex shell written by :class:`wrinkles.shell_output.ShellSeries`, the wall time
of each write, to ``profile_<label>_series.json``. Running it once with the session-1
``wrinkles`` package first on ``PYTHONPATH`` (``git show HEAD:wrinkles/...``) gives the
before/after comparison of the per-frame output cost.

The report also lists the output and bookkeeping functions (XDMF series, summary,
checkpoint) below the top list.

Timings taken while other processes share the machine are contended: compare before/after
runs taken back to back.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from models.backend import MPI
from wrinkles.runner import Run, prepare, run_frames
from wrinkles.scene import load_scene, with_frames

RESULTS = Path(__file__).resolve().parent / "results"


def _args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=Path("scenes/default.toml"))
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--label", default="after", help="output name profile_<label>.txt")
    parser.add_argument("--top", type=int, default=15)
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="scene override (repeatable)")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--series", type=int, nargs=2, default=None,
                        metavar=("VERTICES", "FRAMES"), help="time the shell series writes only")
    return parser.parse_args()


def series_cost(n: int, frames: int, out: Path) -> list[float]:
    """Wall time [s] of each of ``frames`` writes of an ``n``-vertex shell series."""
    import numpy as np

    from wrinkles.shell_output import ShellFrame, ShellSeries

    side = int(np.ceil(np.sqrt(n)))
    g = np.arange(side * side)
    rest = np.column_stack([g % side, g // side, np.zeros(g.size)]).astype(float)
    quads = np.array([i + j * side for j in range(side - 1) for i in range(side - 1)])
    faces = np.concatenate([np.column_stack([quads, quads + 1, quads + side]),
                            np.column_stack([quads + 1, quads + side + 1, quads + side])])
    series = ShellSeries(out / "shell.xdmf", rest, faces, np.zeros(g.size, dtype=np.int64))
    times = []
    for k in range(frames):
        t0 = time.perf_counter()
        series.write(ShellFrame(float(k), np.full_like(rest, k), np.zeros(g.size)))
        times.append(time.perf_counter() - t0)
    return times


def series_main(args: argparse.Namespace) -> None:
    """``--series``: time the shell series writes, print and store them."""
    n, frames = args.series
    with tempfile.TemporaryDirectory(prefix="profile_series_") as tmp:
        times = series_cost(n, frames, Path(tmp))
    marks = sorted({0, frames // 4, frames // 2, frames - 1})
    print(f"shell series, {n} vertices, {frames} frames ({args.label}): write time "
          + ", ".join(f"frame {k}: {times[k] * 1e3:.2f} ms" for k in marks)
          + f"; total {sum(times):.3f} s")
    (args.results / f"profile_{args.label}_series.json").write_text(json.dumps(
        {"vertices": n, "frames": frames, "write_times": times}, indent=2))


def profiled_run(scene_path: Path, frames: int, overrides: list[str],
                 out: Path) -> tuple[Run, cProfile.Profile, float]:
    """Prepare and run the scene under cProfile; return the run, the profile, set-up time."""
    scene = with_frames(load_scene(scene_path, [*overrides, "output.render=false"]), frames)
    t0 = time.perf_counter()
    run = prepare(scene, out, MPI.COMM_WORLD, overwrite=True)
    setup = time.perf_counter() - t0
    profile = cProfile.Profile()
    profile.enable()
    run_frames(run, log=lambda line: print(line, flush=True))
    profile.disable()
    return run, profile, setup


def frame_table(run: Run) -> list[dict[str, Any]]:
    """Per-frame wall time, stage times and shell Newton iterations of a run."""
    return [{"frame": r.frame, "wall_time": r.wall_time, "stage_times": r.stage_times,
             "shell_iterations": r.details.get("shell_iterations")} for r in run.records]


def report_text(rows: list[dict[str, Any]], setup: float, profile: cProfile.Profile,
                top: int, header: str) -> str:
    """The text report: header, frame times, then the top ``top`` cumulative functions."""
    lines = [header, f"set-up (mesh, body, shell build, first output): {setup:.3f} s",
             "frame  wall [s]  stages [s]  shell iterations"]
    for row in rows:
        stages = " ".join(f"{k}={v:.3f}" for k, v in row["stage_times"].items())
        lines.append(f"{row['frame']:5d}  {row['wall_time']:8.3f}  {stages}  "
                     f"{row['shell_iterations']}")
    total = sum(r["wall_time"] for r in rows)
    lines.append(f"total frame time {total:.3f} s, mean {total / max(len(rows), 1):.3f} s")
    stream = io.StringIO()
    stats = pstats.Stats(profile, stream=stream).sort_stats("cumulative")
    stats.print_stats(top)
    stream.write("Output and bookkeeping per run (XDMF series, summary, checkpoint):\n")
    stats.print_stats(r"(output\.py|shell_output\.py|checkpoint\.py):\d+\((write|"
                      r"write_state|_commit|commit_step|_write_xml)\)|runner\.py:\d+\("
                      r"(save_frame|write_summary)\)")
    return "\n".join(lines) + "\n\n" + stream.getvalue()


def main() -> None:
    """Run, profile, print and write the report."""
    args = _args()
    args.results.mkdir(parents=True, exist_ok=True)
    if args.series:
        series_main(args)
        return
    with tempfile.TemporaryDirectory(prefix="profile_frame_") as tmp:
        run, profile, setup = profiled_run(args.scene, args.frames, args.overrides,
                                           Path(tmp) / "out")
    rows = frame_table(run)
    header = (f"profile of {args.scene} --frames {args.frames} "
              f"{' '.join('--set ' + o for o in args.overrides)} ({args.label}; "
              f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, 1 rank, "
              "machine shared with other jobs: timings contended)")
    text = report_text(rows, setup, profile, args.top, header)
    print(text)
    (args.results / f"profile_{args.label}.txt").write_text(text)
    (args.results / f"profile_{args.label}.json").write_text(json.dumps(
        {"scene": str(args.scene), "frames": rows, "setup": setup,
         "overrides": args.overrides}, indent=2))


if __name__ == "__main__":
    main()
