"""Shared helpers of the paper scripts: paths, the command line, JSON output and plot style.

Every script ``paper/scripts/<name>.py`` is run as ``python paper/scripts/<name>.py --build DIR
[--quick]`` (``paper/make_paper.py`` does so) and writes ``DIR/data/<name>.json`` (every number
the paper quotes from it, plus ``"figures"``: the PNG files it wrote under ``DIR/figures``).
The scripts compute their numbers with the functions the tests use (:mod:`validation`), so that
the paper and the test suite measure the same thing.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
DEFAULT_BUILD = REPO / "paper" / "build"
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_CACHE_DIR", str(REPO / ".cache" / "numba"))


def parse_args(description: str, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """``--build DIR`` (default paper/build) and ``--quick`` (tiny sizes, for CI)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--build", type=Path, default=DEFAULT_BUILD, help="build directory")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (CI)")
    return parser.parse_args(argv)


def data_path(build: Path, name: str) -> Path:
    """``build/data/<name>.json``."""
    return build / "data" / f"{name}.json"


def figure_path(build: Path, name: str) -> Path:
    """``build/figures/<name>.png`` (the folder is created)."""
    folder = build / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    return folder / f"{name}.png"


def write_json(build: Path, name: str, data: dict[str, Any], quick: bool,
               started: float) -> Path:
    """Write ``data`` with a ``meta`` entry (mode, wall time, machine) to ``data/<name>.json``."""
    path = data_path(build, name)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = dict(data)
    data["meta"] = {"script": f"paper/scripts/{name}.py", "quick": quick,
                    "wall_time_s": time.perf_counter() - started,
                    "python": platform.python_version(), "machine": platform.machine(),
                    "cpus": os.cpu_count(), "written": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                                      time.gmtime())}
    path.write_text(json.dumps(data, indent=1, default=float) + "\n")
    print(f"wrote {path.relative_to(build)}", flush=True)
    return path


def loglog_figure(path: Path, series: Sequence[tuple[str, Sequence[float], Sequence[float]]],
                  xlabel: str, ylabel: str, title: str) -> str:
    """Log-log plot of ``(label, x, y)`` series; return the path relative to the build dir."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.0, 3.6), dpi=120)
    for label, x, y in series:
        ax.loglog(x, y, "o-", label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return f"figures/{path.name}"


def fitted_slope(x: Any, y: Any) -> float:
    """Least-squares slope of log y against log x (``np.polyfit``; x, y array-like)."""
    import numpy as np

    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])
