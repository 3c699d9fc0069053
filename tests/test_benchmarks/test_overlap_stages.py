"""benchmarks/overlap_stages.py: body and shell stages overlapped over two processes."""

from __future__ import annotations

import pytest
from support import REPO

from benchmarks.overlap_stages import main

FAST = ["shell.subdivision.levels=1", "time.frames=3"]


@pytest.mark.mpi
def test_overlapped_stages_reach_the_serial_shell_bit_for_bit(tmp_path) -> None:
    """The demo at one subdivision level, 3 frames: the overlapped run's shell (rank 1, fed the
    body's displacement frame by frame by rank 0) ends at the serial run's energy exactly."""
    argv = ["--scenes", "ball_sofa_coarse", "--repeat", "1", "--out", str(tmp_path / "o.json")]
    doc = main(argv + [f"--set={item}" for item in FAST])
    (row,) = doc["rows"]
    assert row["serial"]["exit"] == 0 and row["overlapped"]["exit"] == 0, row
    assert row["serial"]["processes"] == 1 and row["overlapped"]["processes"] == 2
    assert row["serial"]["frames"] == row["overlapped"]["frames"] == 3
    assert row["serial"]["shell_energy"] > 0
    assert row["same_energy"] and row["speedup"] > 0


@pytest.mark.mpi
def test_a_scene_without_a_one_way_shell_is_refused(tmp_path) -> None:
    """The two-way bar has one coupled stage: nothing to overlap, both runs refuse it."""
    doc = main(["--scenes", str(REPO / "scenes" / "two_way_bar.toml"), "--repeat", "1",
                "--set=shell.subdivision.levels=1", "--set=time.frames=1",
                "--out", str(tmp_path / "o.json")])
    (row,) = doc["rows"]
    for run in (row["serial"], row["overlapped"]):
        assert run["exit"] != 0
        assert "has no one-way shell stage" in " ".join(run["error"])
    assert "speedup" not in row and doc["median_speedup"] is None
