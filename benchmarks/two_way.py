"""Two-way against one-way frames, side by side in one run, and the skin's effect on the body.

Runs, in this process through the product's own path (:func:`wrinkles.runner.prepare` and
:func:`wrinkles.runner.run_frames`, output files off), one after the other:

* ``one_way``: ``scenes/default.toml`` as shipped (the shell follows the body);
* ``one_way_direct``: the same with the shell's direct solves, the linear method of the
  coupled solve (what the coupling itself costs);
* ``two_way``: ``scenes/two_way_bar.toml`` as shipped (the same scene with the skin acting
  back on the body; the default scheme, one coupled Newton solve per body step,
  :mod:`solvers.monolithic`);
* with ``--fixed-point``: the same two-way scene by the fixed point (``coupling.scheme =
  "implicit"``: body and shell alternated with Anderson on the body load) for comparison.

Per configuration: process CPU time of the frames (:func:`time.process_time` between
progress lines) and wall time, per frame and in all; coupled (or shell) Newton iterations,
factorisations and linear-solve time (factorisation + triangular solves) per iteration. The
effect of the skin: the body displacement of each two-way run against the one-way run (RMS of
the nodal difference relative to the one-way RMS displacement, ``body_rms_rel``), the body's
elastic energy ratio, the shell position difference (``shell_rms_rel``, relative to the
one-way shell's RMS displacement) and each run's dominant wrinkle wavelength
(:func:`benchmarks.speed_accuracy.wrinkle_wavelength`). The time ratio two-way / one-way is
the issue's measure.

Writes ``benchmarks/results/two_way.json`` (``--out``) and prints a table.

Usage::

    python benchmarks/two_way.py
    python benchmarks/two_way.py --frames 2 --fixed-point
    python benchmarks/two_way.py --frames 1 --set shell.subdivision.levels=0   # seconds
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.speed_accuracy import QUIET, wrinkle_wavelength
from models.backend import MPI
from wrinkles.output import write_text_atomic
from wrinkles.runner import prepare, run_frames
from wrinkles.scene import load_scene

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "two_way.json"
CONFIGS: dict[str, tuple[str, list[str]]] = {
    "one_way": ("scenes/default.toml", []),
    "one_way_direct": ("scenes/default.toml", ['shell.solver.method="direct"']),
    "two_way": ("scenes/two_way_bar.toml", []),
    "fixed_point": ("scenes/two_way_bar.toml",
                    ['shell.solver.options."coupling.scheme"="implicit"']),
}


def run_config(scene: str, overrides: list[str], frames: int | None,
               common: list[str] | None = None) -> dict[str, Any]:
    """Run one configuration; return its timings, iteration counts and final state."""
    extra = [*(common or []), *([f"time.frames={frames}"] if frames else [])]
    spec = load_scene(REPO / scene, [*overrides, *extra, *QUIET])
    with tempfile.TemporaryDirectory(prefix="two_way_") as tmp:
        run = prepare(spec, Path(tmp), MPI.COMM_WORLD)
        marks = [time.process_time()]
        run_frames(run, log=lambda line: marks.append(time.process_time())
                   if line.startswith("frame") else None)
    shell = run.shell
    assert shell is not None
    details = [r.details for r in run.records]
    its = [int(d.get("shell_iterations") or 0) for d in details]
    linear = [float(d.get("shell_time_factorize", 0.0)) + float(d.get("shell_time_solve", 0.0))
              for d in details]
    cpu = np.diff(marks[:len(run.records) + 1])
    return {"scene": scene, "overrides": overrides, "frames": len(run.records),
            "cpu_per_frame": [float(c) for c in cpu], "cpu_total": float(cpu.sum()),
            "wall_per_frame": [r.wall_time for r in run.records],
            "iterations": its,
            "coupling_iterations": [d.get("coupling_iterations") for d in details],
            "factorizations": [d.get("shell_factorizations") for d in details],
            "linear_seconds_per_iteration": float(sum(linear) / max(sum(its), 1)),
            "converged": [bool(d.get("shell_converged")) for d in details],
            "elastic": [float(d["elastic"]) for d in details],
            "body_u": np.array(run.body.u.x.array, copy=True),
            "shell": {"rest": shell.rest.copy(), "x": shell.x.copy(), "target": shell.y.copy(),
                      "faces": shell.topology.faces.copy()}}


def rms(a: np.ndarray) -> float:
    """Root mean square of the rows' Euclidean norms."""
    return float(np.sqrt(np.mean(np.sum(np.reshape(a, (len(a), -1)) ** 2, axis=1))))


def effect(one: dict[str, Any], two: dict[str, Any]) -> dict[str, Any]:
    """The skin's effect: body and shell of ``two`` against the one-way run ``one``."""
    u1, u2 = one["body_u"].reshape(-1, 3), two["body_u"].reshape(-1, 3)
    s1, s2 = one["shell"], two["shell"]
    return {"body_rms_rel": rms(u2 - u1) / rms(u1),
            "body_max_diff_m": float(np.abs(u2 - u1).max()),
            "elastic_ratio": [b / a for a, b in zip(one["elastic"], two["elastic"],
                                                     strict=True)],
            "shell_rms_rel": rms(s2["x"] - s1["x"]) / rms(s1["x"] - s1["rest"]),
            "wavelength_m": wrinkle_wavelength(two["shell"])}


def table(rows: dict[str, dict[str, Any]]) -> str:
    """The printed comparison."""
    base = rows["one_way"]["cpu_total"] / rows["one_way"]["frames"]
    lines = [f"{'config':12s} {'frames':>6s} {'CPU s/frame':>11s} {'x one-way':>9s} "
             f"{'its/frame':>9s} {'fact':>5s} {'lin s/it':>8s} {'body rms_rel':>12s} "
             f"{'lambda [m]':>10s}"]
    for name, r in rows.items():
        per = r["cpu_total"] / r["frames"]
        eff = r.get("effect", {})
        lam = eff.get("wavelength_m", r.get("wavelength_m"))
        lines.append(f"{name:12s} {r['frames']:6d} {per:11.2f} {per / base:9.2f} "
                     f"{np.mean(r['iterations']):9.1f} {sum(r['factorizations']):5d} "
                     f"{r['linear_seconds_per_iteration']:8.3f} "
                     f"{eff.get('body_rms_rel', 0.0):12.3f} "
                     f"{lam if lam is None else round(lam, 4)!s:>10s}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the configurations, print the table, write the JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=None, help="frames of every run (default: "
                   "the scenes' own, 4)")
    p.add_argument("--fixed-point", action="store_true",
                   help="also run the two-way scene by the fixed point (slow)")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="scene override applied to every run")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    names = ["one_way", "one_way_direct", "two_way"] + (["fixed_point"] if args.fixed_point
                                                          else [])
    rows: dict[str, dict[str, Any]] = {}
    for name in names:
        scene, overrides = CONFIGS[name]
        print(f"running {name}: {scene} {' '.join(overrides)}", flush=True)
        rows[name] = run_config(scene, overrides, args.frames, args.overrides)
    rows["one_way"]["wavelength_m"] = wrinkle_wavelength(rows["one_way"]["shell"])
    for name in names[2:]:
        rows[name]["effect"] = effect(rows["one_way"], rows[name])
    rows["one_way_direct"]["wavelength_m"] = wrinkle_wavelength(rows["one_way_direct"]["shell"])
    text = table(rows)
    print(text)
    doc = {"machine": {"node": platform.node(), "cpus": os.cpu_count(),
                       "load_avg_1min": os.getloadavg()[0]},
           "overrides": args.overrides, "frames": args.frames,
           "table": text,
           "rows": {k: {kk: vv for kk, vv in v.items() if kk not in ("body_u", "shell")}
                    for k, v in rows.items()}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out, json.dumps(doc, indent=1))
    return doc


if __name__ == "__main__":
    main()
