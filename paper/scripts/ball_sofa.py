"""The draft's experiment: a rigid ball dropped on the elastic sofa (two-way coupling).

Runs ``python -m wrinkles run scenes/ball_sofa_coarse.toml --frames 10 --out
BUILD/runs/ball_sofa`` through ``validation.scene_runs.run_scene``; quick mode keeps one shell
subdivision level and does not render (the settings of
``tests/test_wrinkles/test_scene_ball_sofa.py``), the full mode keeps the scene's two levels and its
render and copies the shell frame of deepest penetration to ``figures/scene_ball_sofa.png``. (The
75-frame ``scenes/ball_sofa.toml`` takes about 10 min on the shared machine: too slow for the
paper build.) The numbers are read from the run's ``summary.json`` as the tests read them: per
frame ``details.balls[0]`` (centre, velocity, contact force, penetration as a fraction of the
radius), ``details.rigid_iterations`` (body solves per coupled step) and ``details.momentum``
(impulse on the ball, on the sofa, of the contact and of the ground). Writes
``data/ball_sofa.json`` and ``figures/ball_sofa.png`` (height, vertical velocity and contact force
against time). The scene then runs again on two ranks (``mpiexec -n 2``, no render): the
layout it takes (``run.layout``), its frames' wall time and whether its frames are the serial
ones bit for bit (``two_ranks``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import figure_path, parse_args, write_json

from wrinkles.launch import python_on_ranks

SCENE = "ball_sofa_coarse"
FRAMES = ("--frames", "10")
QUICK = ("--set", "shell.subdivision.levels=1", "--set", "output.render=false")


def run(out: Path, quick: bool) -> float:
    """Run the coarse ball-on-sofa scene (10 frames); return its wall time [s]."""
    from validation.scene_runs import run_scene

    if out.exists():
        shutil.rmtree(out)  # a fresh run, never a resume of an older one
    started = time.perf_counter()
    proc = run_scene(SCENE, out, *FRAMES, *(QUICK if quick else ()), timeout=7200)
    if proc.returncode != 0:
        raise SystemExit(f"scene {SCENE} failed (exit {proc.returncode}):\n{proc.stderr}")
    return time.perf_counter() - started


COMPARED: tuple[str, ...] = ("energy", "newton_iterations", "shell_energy", "shell_iterations")
"""Frame record entries the two-rank run must reproduce exactly."""


def two_ranks(out: Path, quick: bool, serial: Path) -> dict[str, Any]:
    """Run the scene on two ranks; its layout, frames' wall time and equality with ``serial``."""
    if out.exists():
        shutil.rmtree(out)
    repo = Path(__file__).resolve().parents[2]
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    cmd = [*python_on_ranks(2), "-m",
           "wrinkles", "run", str(repo / "scenes" / f"{SCENE}.toml"), "--out", str(out),
           *FRAMES, *(QUICK if quick else ()), "--set", "output.render=false"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=7200, cwd=repo, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"scene {SCENE} on two ranks failed (exit {proc.returncode}):\n"
                         f"{proc.stderr}")
    runs = [json.loads((d / "summary.json").read_text()) for d in (serial, out)]

    def entries(summary: dict[str, Any]) -> list[list[Any]]:
        return [[f.get(k, f["details"].get(k)) for k in COMPARED] for f in summary["frames"]]

    return {"layout": runs[1]["run"]["layout"],
            "frame_wall_time_s": sum(f["wall_time"] for f in runs[1]["frames"]),
            "same_frames": entries(runs[0]) == entries(runs[1])}


def series(frames: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """Per-frame arrays of the (first) ball: time, height, vertical velocity, force, penetration."""
    balls = [f["details"]["balls"][0] for f in frames]
    return {"time": np.array([f["time"] for f in frames]),
            "height": np.array([b["center"][2] for b in balls]),
            "vz": np.array([b["velocity"][2] for b in balls]),
            "force": np.array([b["contact_force"][2] for b in balls]),
            "penetration": np.array([b["penetration"] for b in balls])}


def frame_step(scene: dict[str, Any]) -> tuple[float, float]:
    """Frame duration ``dt * steps_per_frame`` [s] and the vertical gravity ``g_z``."""
    return (scene["body"]["dt"] * scene["time"]["steps_per_frame"],
            scene["body"]["gravity"][2])


def impact_numbers(s: dict[str, np.ndarray], scene: dict[str, Any]) -> dict[str, Any]:
    """Impact frame (first with a contact force), impact and rebound speeds.

    The impact speed is the free-fall speed ``|w_{k-1} + g_z T|`` the ball would have at the
    end of the first contact frame ``k`` (frame duration ``T``), the definition of
    ``tests/test_wrinkles/test_scene_ball_sofa.py``; the rebound speed is the largest upward
    velocity after it.
    """
    contact = np.flatnonzero(s["force"] > 0.0)
    if contact.size == 0:
        raise SystemExit("the ball never touched the sofa: no impact to report")
    hit = int(contact[0])
    period, g_z = frame_step(scene)
    before = s["vz"][hit - 1] if hit > 0 else scene["rigid"]["balls"][0]["velocity"][2]
    return {"impact_frame": hit + 1, "impact_time": float(s["time"][hit]),
            "impact_speed": abs(float(before) + g_z * period),
            "rebound_speed": max(0.0, float(s["vz"][hit:].max())),
            "rebound_frame": int(np.argmax(s["vz"][hit:])) + hit + 1}


def momentum_residual(frames: list[dict[str, Any]]) -> dict[str, float]:
    """Momentum balance: max over frames of ``|I_ball + I_sofa|`` relative to ``max |I_ball|``.

    ``I_ball`` is the ball's momentum change since the start minus gravity, ``I_sofa`` the
    sofa's minus its gravity and the ground's impulse (``BallCoupling.balance`` of
    models/rigid.py, cumulative); Newton's third law makes them cancel.
    """
    moms = [{k: np.asarray(v, float) for k, v in f["details"]["momentum"].items()}
            for f in frames]
    scale = max(float(np.abs(m["ball_impulse"]).max()) for m in moms)
    residual = max(float(np.abs(m["ball_impulse"] + m["body_impulse"]).max()) for m in moms)
    return {"ball_impulse_max": scale, "momentum_residual": residual,
            "momentum_residual_rel": residual / scale,
            "ground_impulse_z": float(moms[-1]["ground_impulse"][2])}


def summary_numbers(out: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Every number of the paper from the run's ``summary.json``, and the time series."""
    summary = json.loads((out / "summary.json").read_text())
    frames, scene = summary["frames"], summary["scene"]
    s = series(frames)
    ball = scene["rigid"]["balls"][0]
    deepest = int(np.argmax(s["penetration"]))
    numbers = {"frames": len(frames), "shell_vertices": summary["run"]["shell"]["vertices"],
               "body_vertices": summary["run"]["mesh"]["vertices"],
               "body_cells": summary["run"]["mesh"]["cells"],
               "frame_wall_time_s": sum(f["wall_time"] for f in frames),
               "radius": ball["radius"], "mass": ball["mass"],
               "initial_speed": float(np.linalg.norm(ball["velocity"])),
               "dt": scene["body"]["dt"], "steps_per_frame": scene["time"]["steps_per_frame"],
               "max_penetration_rel": float(s["penetration"].max()),
               "deepest_frame": deepest + 1, "deepest_time": float(s["time"][deepest]),
               "max_rigid_iterations": max(max(f["details"]["rigid_iterations"])
                                           for f in frames),
               "contact_force_peak": float(s["force"].max()),
               "weight": ball["mass"] * abs(scene["body"]["gravity"][2]),
               **impact_numbers(s, scene), **momentum_residual(frames)}
    numbers["restitution"] = numbers["rebound_speed"] / numbers["impact_speed"]
    numbers["series"] = {k: v.tolist() for k, v in s.items()}
    return numbers, s


def plot(path: Path, s: dict[str, np.ndarray], impact_time: float) -> str:
    """Ball height, vertical velocity and contact force against time (three stacked panels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(5.0, 6.0), dpi=120, sharex=True)
    for ax, key, label in zip(axes, ("height", "vz", "force"),
                              ("centre height [m]", "vertical velocity [m/s]",
                               "contact force z [N]"), strict=True):
        ax.plot(s["time"], s[key], "o-", ms=3)
        ax.axvline(impact_time, color="grey", ls="--", lw=0.8)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[0].set_title("Rigid ball on the elastic sofa (dashed: end of the first contact frame)",
                      fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return f"figures/{path.name}"


def copy_render(out: Path, build: Path, when: float) -> str:
    """Copy the runner's render ``frames/shell_KKKK.png`` of the shell step at time ``when``."""
    from wrinkles.shell_output import SHELL_XDMF_NAME, step_sources

    times, _ = step_sources(out / SHELL_XDMF_NAME)
    k = int(np.argmin(np.abs(np.asarray(times, float) - when)))
    source = out / "frames" / f"shell_{k:04d}.png"
    if not source.is_file():
        raise SystemExit(f"{source} missing: the run did not render its frames")
    target = figure_path(build, "scene_ball_sofa")
    shutil.copyfile(source, target)
    return f"figures/{target.name}"


def main() -> None:
    """Run the scene, measure, plot and write ``data/ball_sofa.json``."""
    args = parse_args(__doc__ or "")
    started = time.perf_counter()
    out = args.build / "runs" / "ball_sofa"
    wall = run(out, args.quick)
    numbers, s = summary_numbers(out)
    numbers["two_ranks"] = two_ranks(args.build / "runs" / "ball_sofa_2ranks", args.quick, out)
    figures = [plot(figure_path(args.build, "ball_sofa"), s, numbers["impact_time"])]
    if not args.quick:
        numbers["render"] = copy_render(out, args.build, numbers["deepest_time"])
        figures.append(numbers["render"])
    write_json(args.build, "ball_sofa", {"wall_time_s": wall, **numbers, "figures": figures},
               args.quick, started)


if __name__ == "__main__":
    main()
