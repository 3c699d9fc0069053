"""How long the ``wrinkles`` commands that run no frame take, from the prompt to their exit.

``wrinkles --help``, ``wrinkles check SCENE``, ``wrinkles view RUN``, ``wrinkles plot RUN``
and ``wrinkles render RUN``, each as a user starts it (a new interpreter, the CLI's own
imports included), on a run this script makes first (one frame of ``--scene`` with
``output.render = false``). With ``--before REV`` the same commands of the code at ``REV``
(a detached worktree) alternate with this code's, ``--repeat`` times each; the table shows
the median and the range of the wall times.

Usage::

    python benchmarks/cli_start.py [--scene default] [--repeat 5] [--before REV]

Writes ``benchmarks/results/cli_start.json`` (``--out``).
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

from benchmarks.product_frames import drop_worktree, scene_path, worktree

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "cli_start.json"


def commands(scene: Path, run: Path) -> dict[str, list[str]]:
    """The timed commands: name -> arguments after ``wrinkles``."""
    return {"--help": ["--help"], "check": ["check", str(scene)], "view": ["view", str(run)],
            "plot": ["plot", str(run)], "render": ["render", str(run)]}


def wrinkles(code: Path, args: list[str]) -> float:
    """Run ``python -m wrinkles ARGS`` of the tree ``code``; its wall time (exit 0 required)."""
    env = dict(os.environ, PYTHONPATH=str(code))
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "wrinkles", *args], cwd=code, env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    wall = time.perf_counter() - start
    if proc.returncode:
        raise SystemExit(f"wrinkles {' '.join(args)} ({code}) exited {proc.returncode}: "
                         f"{proc.stderr.strip()[-400:]}")
    return wall


def main() -> dict[str, Any]:
    """Time the commands (and those of ``--before``); print the table, write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="default", help="scene name or .toml path")
    parser.add_argument("--repeat", type=int, default=5, help="runs of each command and code")
    parser.add_argument("--before", default=None, help="also time the code at this revision")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    scene = scene_path(args.scene)
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        wrinkles(REPO, ["run", str(scene), "--out", str(run), "--frames", "1", "--set",
                        "output.render=false"])
        codes = {"this": REPO}
        if args.before:
            codes[args.before] = worktree(args.before, Path(tmp))
        try:
            times: dict[str, dict[str, list[float]]] = {c: {} for c in codes}
            for _ in range(args.repeat):
                for name, argv in commands(scene, run).items():
                    for code, path in codes.items():  # alternating: the same machine state
                        times[code].setdefault(name, []).append(wrinkles(path, argv))
        finally:
            for code, path in codes.items():
                if code != "this":
                    drop_worktree(path)
    print(f"{'command':>10} {'code':>10} {'median s':>9} {'min s':>7} {'max s':>7}")
    for name in times["this"]:
        for code in codes:
            t = times[code][name]
            print(f"{name:>10} {code:>10} {statistics.median(t):9.2f} {min(t):7.2f} "
                  f"{max(t):7.2f}")
    doc = {"scene": str(scene), "repeat": args.repeat, "before": args.before, "times": times}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2))
    print(f"wrote {args.out}")
    return doc


if __name__ == "__main__":
    main()
