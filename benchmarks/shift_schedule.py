"""Shell Newton time against the shifted-Hessian schedule, on the wrinkle scenes.

Far from a wrinkled minimum the exact shell Hessian is indefinite (the flat start of
scenes/default.toml has about 1200 negative eigenvalues), and every Newton iteration solves
with ``A + tau I`` (:func:`solvers.linear.shift_candidates`): shifts grow by
``shell.newton.shift.growth`` until the factorisation is positive definite and the line search
accepts the step, and the next iteration starts from ``tau / shell.newton.shift_decay``. A
shift larger than needed shortens the step in every soft direction; a start too small pays a
failed factorisation. This benchmark runs whole scenes (``wrinkles run``, one process each,
output and rendering as the scene has them except the render) with each ``growth/decay``
pair and records per frame the shell Newton iterations, factorisations, shifted iterations,
shell Newton wall time and the final shell energy, and the process CPU time of the run.

The shell energies of two schedules may differ at a wrinkled frame: a path from the flat
start falls into a wrinkle branch that depends on its step lengths (both are minima; the
accuracy against a reference is measured by ``benchmarks/speed_accuracy.py``).

Usage::

    python benchmarks/shift_schedule.py                          # 4 scenes x 9 schedules
    python benchmarks/shift_schedule.py --schedules 10/10 5/2 --scenes default
    python benchmarks/shift_schedule.py --quick                  # 1 frame, 1 level (seconds)

Prints a table and writes benchmarks/results/shift_schedule.json (rewritten after every run).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "shift_schedule.json"
SCENES: tuple[str, ...] = ("default", "bent_bar", "twisted_cylinder", "ball_sofa_coarse")
SCHEDULES: tuple[str, ...] = ("10/10", "5/2", "4/2", "6/2", "8/3", "3/3", "4/4", "3/1.5",
                              "2/1.5")
"""``growth/decay`` pairs: the solver's ten-fold default, the presets' 5 / 2, IPOPT's 8 / 3
(Waechter & Biegler 2006, kappa_w^+ and 1 / kappa_w^-) and their neighbours."""
CEILING: float = 1e13
"""Largest shift relative to the first (``initial``): ``max_shifts`` is chosen per growth so
that ``growth^(max_shifts - 1) >= CEILING``, the reach of 14 ten-fold shifts."""


def schedule_overrides(schedule: str) -> list[str]:
    """``--set`` arguments of a ``growth/decay`` pair (with the matching ``max_shifts``)."""
    growth, decay = (float(v) for v in schedule.split("/"))
    shifts = math.ceil(math.log(CEILING) / math.log(growth)) + 1
    return ["--set", f"shell.newton.shift.growth={growth!r}",
            "--set", f"shell.newton.shift_decay={decay!r}",
            "--set", f"shell.newton.shift.max_shifts={shifts}"]


def child_cpu() -> float:
    """Process CPU seconds (user + system) of the finished child processes so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_scene(scene: str, schedule: str, extra: list[str]) -> dict:
    """One ``wrinkles run`` of ``scenes/<scene>.toml`` with ``schedule``; its row."""
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "wrinkles", "run", str(REPO / "scenes" / f"{scene}.toml"),
               "--out", out, "--set", "shell.render=false", *schedule_overrides(schedule),
               *extra]
        cpu0 = child_cpu()
        done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=False)
        cpu = child_cpu() - cpu0
        if done.returncode != 0:
            return {"scene": scene, "schedule": schedule, "error": done.stderr[-2000:],
                    "cpu": cpu}
        frames = json.loads((Path(out) / "summary.json").read_text())["frames"]
    details = [f["details"] for f in frames]
    return {"scene": scene, "schedule": schedule, "cpu": cpu,
            "iterations": [d["shell_iterations"] for d in details],
            "factorizations": [d["shell_factorizations"] for d in details],
            "shifted": [d["shell_shifted_iterations"] for d in details],
            "shell_seconds": [d["shell_time_total"] for d in details],
            "converged": [d["shell_converged"] for d in details],
            "final_energy": details[-1]["shell_energy"]}


def print_row(r: dict) -> None:
    """One line of the table."""
    if "error" in r:
        print(f"{r['scene']:>17} {r['schedule']:>6}  failed: {r['error'].splitlines()[-1:]}",
              flush=True)
        return
    print(f"{r['scene']:>17} {r['schedule']:>6} {sum(r['iterations']):>5} "
          f"{sum(r['factorizations']):>6} {sum(r['shifted']):>7} {sum(r['shell_seconds']):8.1f} "
          f"{r['cpu']:8.1f} {r['final_energy']:13.6e}  {r['iterations']}", flush=True)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES))
    p.add_argument("--schedules", nargs="+", default=list(SCHEDULES), metavar="GROWTH/DECAY")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="extra scene override for every run")
    p.add_argument("--quick", action="store_true",
                   help="scenes/default.toml, 1 frame, 1 subdivision level, 2 schedules")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.schedules = ["default"], ["10/10", "5/2"]
        args.overrides += ["time.frames=1", "shell.subdivision.levels=1"]
    for schedule in args.schedules:
        parts = schedule.split("/")
        if len(parts) != 2 or not all(_number_above_one(v) for v in parts):
            p.error(f"--schedules: expected GROWTH/DECAY with both > 1, got {schedule!r}")
    return args


def _number_above_one(text: str) -> bool:
    """Whether ``text`` is a number > 1."""
    try:
        return float(text) > 1
    except ValueError:
        return False


def main(argv: list[str] | None = None) -> None:
    """Every (scene, schedule): run, print, write the JSON."""
    args = parse_args(argv)
    extra = [a for o in args.overrides for a in ("--set", o)]
    meta = {"python": platform.python_version(), "cpus": os.cpu_count(),
            "overrides": args.overrides, "ceiling": CEILING,
            "units": "shell_seconds: shell Newton wall time per frame; cpu: process CPU "
                     "seconds of the whole run (body, set-up and output included)"}
    print(f"{'scene':>17} {'sched':>6} {'its':>5} {'fact':>6} {'shifted':>7} {'shell s':>8} "
          f"{'cpu s':>8} {'final W':>13}  its per frame")
    rows: list[dict] = []
    for scene in args.scenes:
        for schedule in args.schedules:
            rows.append(run_scene(scene, schedule, extra))
            print_row(rows[-1])
            meta["load_average"] = os.getloadavg()
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
