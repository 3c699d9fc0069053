"""Shell Newton time against the shifted-Hessian schedule, on the wrinkle scenes.

Far from a wrinkled minimum the exact shell Hessian is indefinite (the flat start of
scenes/default.toml has about 1200 negative eigenvalues), and every Newton iteration solves
with ``A + tau I`` (:func:`solvers.linear.shift_candidates`): shifts grow by
``shell.solver.options.newton.shift.growth`` until the factorisation is positive definite and the
line search accepts the step, and the next iteration starts from ``tau /
shell.solver.options.newton.shift_decay``. A shift larger than needed shortens the step in every
soft direction; a start too small pays a failed factorisation. This benchmark runs whole scenes in
this process (:func:`speed_accuracy.run_config`: serial, no output files, after an untimed JIT
warm-up) with each ``growth/decay`` pair and records per frame the shell Newton iterations,
factorisations, shifted iterations and shell Newton wall time, the final shell energy, and
the process CPU time of all frames.

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
from pathlib import Path

from benchmarks.speed_accuracy import run_config

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "shift_schedule.json"
SCENES: tuple[str, ...] = ("default", "bent_bar", "twisted_cylinder", "ball_sofa_coarse")
SCHEDULES: tuple[str, ...] = ("10/10", "5/2", "4/2", "6/2", "8/3", "3/3", "4/4", "3/1.5",
                              "2/1.5")
"""``growth/decay`` pairs: the solver's ten-fold default, the static scenes' 5 / 2, IPOPT's 8 / 3
(Waechter & Biegler 2006, kappa_w^+ and 1 / kappa_w^-) and their neighbours."""
CEILING: float = 1e13
"""Largest shift relative to the first (``initial``): ``max_shifts`` is chosen per growth so
that ``growth^(max_shifts - 1) >= CEILING``, the reach of 14 ten-fold shifts."""


def schedule_overrides(schedule: str) -> list[str]:
    """Scene overrides of a ``growth/decay`` pair (with the matching ``max_shifts``)."""
    growth, decay = (float(v) for v in schedule.split("/"))
    shifts = math.ceil(math.log(CEILING) / math.log(growth)) + 1
    key = "shell.solver.options.newton"
    return [f"{key}.shift.growth={growth!r}", f"{key}.shift_decay={decay!r}",
            f"{key}.shift.max_shifts={shifts}"]


def run_scene(scene: str, schedule: str, extra: list[str]) -> dict:
    """``scenes/<scene>.toml`` with ``schedule`` (:func:`speed_accuracy.run_config`: serial,
    no output files); its row."""
    run = run_config(REPO / "scenes" / f"{scene}.toml", [*schedule_overrides(schedule), *extra])
    return {"scene": scene, "schedule": schedule, "cpu": sum(run["frame_cpu_times"]),
            "iterations": run["shell_iterations"], "factorizations": run["shell_factorizations"],
            "shifted": run["shell_shifted_iterations"], "shell_seconds": run["shell_seconds"],
            "converged": run["shell_converged"], "final_energy": run["shell_final_energy"]}


def print_row(r: dict) -> None:
    """One line of the table."""
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
    meta = {"python": platform.python_version(), "cpus": os.cpu_count(),
            "overrides": args.overrides, "ceiling": CEILING,
            "units": "shell_seconds: shell Newton wall time per frame; cpu: process CPU "
                     "seconds of all frames (set-up excluded, no output files)"}
    print(f"{'scene':>17} {'sched':>6} {'its':>5} {'fact':>6} {'shifted':>7} {'shell s':>8} "
          f"{'cpu s':>8} {'final W':>13}  its per frame")
    run_config(REPO / "scenes" / "default.toml", ["shell.subdivision.levels=0", "time.frames=1",
                                                  *args.overrides])  # JIT warm-up, untimed
    rows: list[dict] = []
    for scene in args.scenes:
        for schedule in args.schedules:
            rows.append(run_scene(scene, schedule, args.overrides))
            print_row(rows[-1])
            meta["load_average"] = os.getloadavg()
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
