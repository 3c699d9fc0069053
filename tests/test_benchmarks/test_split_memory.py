"""benchmarks/split_memory.py measures the shell's peak memory per rank at 1 and 2 ranks."""

from __future__ import annotations

import json

import pytest

from benchmarks.split_memory import main


@pytest.mark.mpi
def test_two_rank_run_records_every_rank_and_its_ratio(tmp_path) -> None:
    """The default scene at 1 level (172 vertices), 1 and 2 ranks: each rank's shell peak is
    its peak resident set less the one before the shell, the PETSc and Python peaks are
    measured (non-zero), and the ratios are the largest rank's over the serial run's."""
    out = tmp_path / "m.json"
    doc = main(["--levels", "1", "--ranks", "1", "2", "--out", str(out)])
    one, two = doc["runs"]
    assert one["ranks"] == 1 and two["ranks"] == 2 and len(two["per_rank"]) == 2
    for row in one["per_rank"] + two["per_rank"]:
        assert row["shell_peak"] == pytest.approx(row["rss_peak"] - row["rss_before_shell"])
        assert row["rss_before_shell"] > 0 and row["petsc_peak"] > 0 and row["python_peak"] > 0
    serial = one["per_rank"][0]
    worst = max(r["shell_peak"] for r in two["per_rank"])
    assert doc["ratios"]["2"]["shell_peak"] == pytest.approx(worst / serial["shell_peak"])
    assert json.loads(out.read_text())["ratios"] == doc["ratios"]
