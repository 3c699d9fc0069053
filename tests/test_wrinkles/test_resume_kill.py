"""No run loses its frames: SIGKILL a run at random moments, check the files, ``--resume``.

The run is a block dropped on the ground (implicit Euler, penalty contact; written here, so
that edits of ``scenes/`` do not change the test) with 10 sub-steps of
1 ms per 10 ms frame, so a frame takes ~0.2 s and a kill lands anywhere in a frame: in the
Newton solves, in the XDMF append (``.work/``), in the commit renames or in the summary and
checkpoint writes. After every kill the committed ``body.xdmf`` / ``body.h5`` must parse and
every step in the XML must be readable; the resumed run must then reproduce a straight run.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from killrun import kill_after_frames
from support import (
    FRAMES,
    assert_same_as,
    assert_series_intact,
    progress_lines,
    run_args,
    wrinkles,
)


def start_and_kill(out: Path, after: int, delay: float, *extra: str) -> int:
    """Start a run, SIGKILL it ``delay`` s after ``after`` frames are done; return frames done."""
    return kill_after_frames(run_args(out, *extra), out, after, delay, timeout=120)




@pytest.fixture(scope="module")
def straight(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("straight") / "out"
    proc = wrinkles(*run_args(out))
    assert proc.returncode == 0, proc.stderr
    return out






@pytest.mark.parametrize("delays", [(0.0, 0.05, 0.13), (0.02, 0.09, 0.17)])
def test_killed_three_times_then_resumed_matches_straight_run(straight, tmp_path, delays):
    out = tmp_path / "out"
    done = start_and_kill(out, 2, delays[0])
    assert done >= 2
    seen = [assert_series_intact(out, done)]
    for delay in delays[1:]:
        done = start_and_kill(out, done + 1, delay, "--resume")
        seen.append(assert_series_intact(out, done))
    print(f"steps on disk after each kill: {seen}")
    proc = wrinkles(*run_args(out, "--resume"))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert [r["frame"] for r in summary["frames"]] == list(range(1, FRAMES + 1))
    assert len(summary["run"]["restarts"]) == 3
    assert_same_as(straight, out, atol_rel=1e-12)  # state restored exactly: same iterates


def test_restart_is_an_alias_of_resume(straight, tmp_path):
    out = tmp_path / "out"
    assert wrinkles(*run_args(out)[:3], "5", *run_args(out)[4:]).returncode == 0
    proc = wrinkles(*run_args(out, "--restart"))
    assert proc.returncode == 0, proc.stderr
    assert [line.split()[1] for line in progress_lines(proc.stdout)][0] == f"6/{FRAMES}"
    assert_same_as(straight, out, atol_rel=1e-12)


def test_damaged_work_copy_never_reaches_the_committed_series(tmp_path):
    """A kill during the append damages only ``.work/``: the next run overwrites it."""
    out = tmp_path / "out"
    assert wrinkles(*run_args(out)[:3], "3", *run_args(out)[4:]).returncode == 0
    work = out / ".work"
    assert not work.exists()  # a completed run leaves no work copy behind
    work.mkdir()  # as a kill in the middle of the next append would leave it
    (work / "body.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 64)  # truncated HDF5
    (work / "body.xdmf").write_text("<Xdmf><Domain><Grid")  # half-written XML
    assert assert_series_intact(out, 3) == 4
    proc = wrinkles(*run_args(out, "--resume")[:3], "5", *run_args(out, "--resume")[4:])
    assert proc.returncode == 0, proc.stderr
    assert assert_series_intact(out, 5) == 6
