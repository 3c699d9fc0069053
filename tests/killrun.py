"""Start a `wrinkles` run in a subprocess and SIGKILL it mid-run (shared by the resume tests)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def frames_done(out: Path) -> int:
    """Completed frames according to ``summary.json`` (written atomically)."""
    try:
        return len(json.loads((out / "summary.json").read_text())["frames"])
    except (OSError, ValueError, KeyError):
        return 0


def kill_after_frames(cli_args: list[str], out: Path, after: int, delay: float,
                      timeout: float = 180.0) -> int:
    """Run ``python -m wrinkles CLI_ARGS``, SIGKILL it ``delay`` s after ``after`` frames are done.

    Returns:
        The number of frames completed on disk when the process died.
    """
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-m", "wrinkles", *cli_args], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout
    while frames_done(out) < after and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    return frames_done(out)
