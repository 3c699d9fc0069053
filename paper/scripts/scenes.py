"""Run the default, bent-bar and twisted-cylinder scenes from the CLI, render, measure.

Each scene runs as ``python -m wrinkles run scenes/<name>.toml --out BUILD/runs/<name>``
(quick mode: the coarse settings of :data:`validation.scene_runs.COARSE`: the full load in 2
frames, one subdivision level). The last frame of the shell is rendered with
``wrinkles/render.py`` into ``figures/scene_<name>.png``; the physical numbers are those of the
tests (``bent_bar_metrics``, ``twisted_cylinder_metrics``); sizes, iterations and wall
times come from the run's ``summary.json``. Writes ``data/scenes.json``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

from common import figure_path, parse_args, write_json

SCENES = ("default", "bent_bar", "twisted_cylinder")
QUICK_DEFAULT = ("--frames", "2", "--set", "body.dt=0.5", "--set",
                 "shell.subdivision.levels=1", "--set", "output.render=false")


def run(name: str, out: Path, quick: bool) -> float:
    """Run one scene (rendering off: the paper renders the last frame); return wall time."""
    from validation.scene_runs import COARSE, run_scene

    extra = (COARSE if name != "default" else QUICK_DEFAULT) if quick else (
        "--set", "output.render=false")
    started = time.perf_counter()
    proc = run_scene(name, out, *extra, timeout=7200)
    if proc.returncode != 0:
        raise SystemExit(f"scene {name} failed (exit {proc.returncode}):\n{proc.stderr}")
    return time.perf_counter() - started


def render_last(out: Path, figure: Path) -> None:
    """Render the last stored shell step of a run into ``figure`` (off-screen)."""
    from wrinkles.render import RenderOptions, colour_range, polydata, render_frame
    from wrinkles.shell_output import SHELL_XDMF_NAME, read_shell_series

    rest, faces, _, frames = read_shell_series(out / SHELL_XDMF_NAME)
    opts = RenderOptions(width=800, height=520)
    render_frame(polydata(rest, faces, frames[-1]), figure, colour_range(frames, opts), opts)


def summary_numbers(out: Path) -> dict[str, Any]:
    """Sizes, iterations, amplitude and timings of a run from its ``summary.json``."""
    summary = json.loads((out / "summary.json").read_text())
    frames, shell = summary["frames"], summary["run"]["shell"]
    last = frames[-1]["details"]
    return {"frames": len(frames), "body_vertices": summary["run"]["mesh"]["vertices"],
            "body_cells": summary["run"]["mesh"]["cells"], "shell_vertices": shell["vertices"],
            "clusters": shell["clusters"]["count"], "frame_wall_time_s":
            sum(f["wall_time"] for f in frames), "shell_iterations":
            sum(f["details"]["shell_iterations"] for f in frames), "body_newton_iterations":
            sum(f["newton_iterations"] for f in frames), "wrinkle_amplitude_max":
            last["wrinkle_amplitude"], "wrinkle_amplitude_rel": last["wrinkle_amplitude_rel"],
            "mean_edge_length": shell["mean_edge_length"], "k_L": shell["k_L"],
            "k_B": shell["k_B"], "k_P": shell["k_P"],
            "cluster_spacing": shell["clusters"]["spacing"],
            "cluster_sigma": shell["clusters"]["sigma"], "inputs": summary["scene"],
            "load_parameter": frames[-1]["time"], "versions": summary["versions"]}


def skin_numbers(scene: dict[str, Any]) -> dict[str, float]:
    """Skin/body stiffness ratio and the wavelength lambda = 2 pi h (Ebar_f / (3 Ebar_s))^(1/3).

    ``Ebar = E / (1 - nu^2)`` (plane strain moduli; Remillard & Kry 2013, after Cerda &
    Mahadevan 2003).
    """
    skin, body = scene["shell"]["skin"], scene["material"]
    ebar_f = skin["E"] / (1.0 - skin["nu"] ** 2)
    ebar_s = body["E"] / (1.0 - body["nu"] ** 2)
    return {"skin_body_ratio": skin["E"] / body["E"], "skin_thickness": skin["thickness"],
            "wavelength_theory": 2.0 * math.pi * skin["thickness"]
            * (ebar_f / (3.0 * ebar_s)) ** (1.0 / 3.0)}


def scene_entry(name: str, build: Path, quick: bool) -> dict[str, Any]:
    """Run, render and measure one scene."""
    from validation.scene_runs import bent_bar_metrics, twisted_cylinder_metrics

    out = build / "runs" / name
    wall = run(name, out, quick)
    figure = figure_path(build, f"scene_{name}")
    render_last(out, figure)
    entry = {"wall_time_s": wall, **summary_numbers(out), "figure": f"figures/{figure.name}"}
    metrics = {"bent_bar": bent_bar_metrics,
               "twisted_cylinder": twisted_cylinder_metrics}.get(name)
    if metrics is not None:
        entry.update(metrics(out))
    entry.update(skin_numbers(entry["inputs"]))
    if name == "twisted_cylinder":
        omega = entry["inputs"]["body"]["pins"][1]["angular_velocity"]
        entry["prescribed_angle"] = math.hypot(*omega) * entry["load_parameter"]
        entry["end_angle_error"] = abs(entry["end_angle"] - entry["prescribed_angle"])
    return entry


def main() -> None:
    """Run all scenes and write ``data/scenes.json``."""
    args = parse_args(__doc__ or "")
    started = time.perf_counter()
    scenes = {name: scene_entry(name, args.build, args.quick) for name in SCENES}
    write_json(args.build, "scenes", {**scenes, "figures": [s["figure"] for s in
                                                            scenes.values()]},
               args.quick, started)


if __name__ == "__main__":
    main()
