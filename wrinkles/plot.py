"""``wrinkles plot RUN``: one PNG of a run's per-frame numbers, read from its ``summary.json``.

Four panels over the frame number: the energies (body total, shell terms), the Newton
iterations (body, shell, a red cross where the shell stopped above its tolerance; coupling
iterations of two-way frames), the wall time per stage (and, for a run whose stages overlap on
two ranks, the body rank's own time per frame as a dashed line), and
the smallest ``det F`` with the wrinkle amplitude (normal offset over the mean edge length).
Energies that change sign are drawn on a symmetric-log axis. Written as ``RUN/plots.png``
(matplotlib, Agg backend: no display needed).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from meshes.errors import InputError

PLOT_NAME = "plots.png"


def read_summary(run: Path) -> dict[str, Any]:
    """Return the run's ``summary.json``; InputError naming the file when it is unusable."""
    path = run / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no summary (is {run} the output directory of a run?)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the summary ({exc})") from None
    if not isinstance(summary, dict) or not summary.get("frames"):
        raise InputError(f"{path}: no completed frame to plot")
    return summary


def series(frames: list[dict[str, Any]], key: str) -> np.ndarray:
    """Per-frame values of ``key`` (a record field or a ``details`` entry); NaN where absent."""
    values = []
    for record in frames:
        value = record.get(key, record.get("details", {}).get(key))
        values.append(float(value) if isinstance(value, int | float) else np.nan)
    return np.array(values)


def plot_run(run: Path, width: float = 11.0, height: float = 8.0) -> Path:
    """Draw the four panels of a run into ``run/plots.png``; return the path."""
    import matplotlib.pyplot as plt

    fig = summary_figure(read_summary(run), run.name, width, height)
    path = run / PLOT_NAME
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def unconverged_frames(frames: list[dict[str, Any]]) -> list[int]:
    """Return the frames whose shell Newton stopped above its tolerance (not converged)."""
    return [int(r["frame"]) for r in frames
            if r.get("details", {}).get("shell_converged") is False]


def self_intersecting_frames(frames: list[dict[str, Any]]) -> list[int]:
    """Return the frames whose shell passes through itself (``shell_self_intersections``)."""
    return [int(r["frame"]) for r in frames
            if r.get("details", {}).get("shell_self_intersections", 0) > 0]


def summary_figure(summary: dict[str, Any], name: str, width: float = 11.0,
                   height: float = 8.0) -> Any:
    """Draw the four panels of :func:`plot_run` into a new figure (``name``: fallback title).

    Frames whose shell solve stopped above its tolerance are marked with a red cross on the
    shell's iteration curve, labelled "shell NOT converged"; frames whose shell passes through
    itself with a magenta ring, labelled "shell self-intersecting". The title counts both.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = summary["frames"]
    k = np.array([r["frame"] for r in frames])
    fig, axes = plt.subplots(2, 2, figsize=(width, height), sharex=True)
    ax = axes[0, 0]
    ax.plot(k, series(frames, "energy"), "o-", label="body total")
    terms = sorted({t for r in frames for t in r.get("details", {}).get("shell_terms", {})})
    for term in terms:
        ax.plot(k, [r.get("details", {}).get("shell_terms", {}).get(term, np.nan)
                    for r in frames], ".-", label=f"shell {term}")
    ax.set_yscale("symlog", linthresh=1e-6)
    ax.set_ylabel("energy [J]")
    ax.legend(fontsize=7)
    ax = axes[0, 1]
    for key, label in (("newton_iterations", "body Newton"), ("shell_iterations", "shell Newton"),
                       ("coupling_iterations", "body/shell coupling")):
        values = series(frames, key)
        if np.isfinite(values).any():
            ax.plot(k, values, "o-", label=label)
    stopped = np.isin(k, unconverged_frames(frames))
    if stopped.any():
        ax.plot(k[stopped], series(frames, "shell_iterations")[stopped], "x", color="red",
                markersize=10, markeredgewidth=2, label="shell NOT converged")
    crossed = np.isin(k, self_intersecting_frames(frames))
    if crossed.any():
        ax.plot(k[crossed], series(frames, "shell_iterations")[crossed], "o", color="magenta",
                markerfacecolor="none", markersize=14, markeredgewidth=2,
                label="shell self-intersecting")
    ax.set_ylabel("iterations per frame")
    ax.legend(fontsize=7)
    ax = axes[1, 0]
    stages = sorted({s for r in frames for s in r.get("stage_times", {})})
    bottom = np.zeros(len(frames))
    for stage in stages:
        times = np.array([r.get("stage_times", {}).get(stage, 0.0) for r in frames])
        ax.bar(k, times, bottom=bottom, label=stage)
        bottom += times
    beside = series(frames, "body_rank_time")  # the overlapped layout's body, on rank 1
    if np.isfinite(beside).any():
        ax.plot(k, beside, "D--", color="black", label="body on rank 1 (overlapped)")
    ax.set_ylabel("wall time per stage [s]")
    ax.set_xlabel("frame")
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    ax.plot(k, series(frames, "min_det_f"), "o-", label="min det F (body)")
    amplitude = series(frames, "wrinkle_amplitude_rel")
    if np.isfinite(amplitude).any():
        ax.plot(k, amplitude, "s-", label="wrinkle amplitude / edge")
    ax.set_xlabel("frame")
    ax.legend(fontsize=7)
    title = summary.get("scene", {}).get("title") or name
    status = summary.get("run", {}).get("status", "?")
    stopped_count = len(unconverged_frames(frames))
    status += f"; shell NOT converged in {stopped_count}" if stopped_count else ""
    crossed_count = len(self_intersecting_frames(frames))
    status += f"; shell self-intersecting in {crossed_count}" if crossed_count else ""
    fig.suptitle(f"{title} ({len(frames)} frames, {status})")
    fig.tight_layout()
    return fig


def add_parser(commands: Any) -> Any:
    """Add the ``plot`` sub-command to an argparse sub-parser collection; return it."""
    parser = commands.add_parser("plot", help="plot a run's per-frame energies, iterations and "
                                 "stage times into RUN/plots.png")
    parser.add_argument("out", type=Path, help="output directory of a run (holds summary.json)")
    return parser


def command_plot(args: argparse.Namespace) -> int:
    """Run the ``plot`` sub-command; return the exit code."""
    print(f"wrote {plot_run(args.out)}", flush=True)
    return 0
