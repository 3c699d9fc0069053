"""Start a `wrinkles` run in a subprocess and SIGKILL it mid-run (shared by the resume tests).

On ``ranks > 1`` the run is ``mpiexec -n RANKS python -m wrinkles ...`` started in a new
session, and SIGKILL goes to that whole process group (mpiexec, its proxy and every rank: a
kill of mpiexec alone would leave the ranks running); the kill returns once none is left.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

from wrinkles.launch import python_on_ranks

REPO = Path(__file__).resolve().parents[1]


def frames_done(out: Path) -> int:
    """Completed frames according to ``summary.json`` (written atomically)."""
    try:
        return len(json.loads((out / "summary.json").read_text())["frames"])
    except (OSError, ValueError, KeyError):
        return 0


def kill_after_frames(cli_args: list[str], out: Path, after: int, delay: float,
                      timeout: float = 180.0, ranks: int = 1) -> int:
    """Run ``python -m wrinkles CLI_ARGS``, SIGKILL it ``delay`` s after ``after`` frames are done.

    Args:
        cli_args: Arguments of ``python -m wrinkles``.
        out: Output directory of the run (its ``summary.json`` counts the frames).
        after: Completed frames to wait for.
        delay: Seconds to wait after that before the kill.
        timeout: Longest wait for the frames.
        ranks: MPI ranks (> 1: under mpiexec, the whole process group is killed).

    Returns:
        The number of frames completed on disk when the process died.
    """
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.Popen([*python_on_ranks(ranks), "-m", "wrinkles", *cli_args], cwd=REPO,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=ranks > 1)
    deadline = time.monotonic() + timeout
    while frames_done(out) < after and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    time.sleep(delay)
    assert proc.poll() is None, "the run ended before it could be killed"
    if ranks > 1:
        os.killpg(proc.pid, signal.SIGKILL)
    else:
        proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    if ranks > 1:
        wait_group_gone(proc.pid)
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    return frames_done(out)


def wait_group_gone(pgid: int, timeout: float = 30.0) -> None:
    """Wait until no process of group ``pgid`` is left (its leader already reaped)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.01)
    raise AssertionError(f"processes of group {pgid} survived SIGKILL")
