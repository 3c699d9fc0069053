"""benchmarks/product_frames.py runs the CLI of this tree and of a git revision side by side."""

from __future__ import annotations

import json
import subprocess

from benchmarks.product_frames import REPO, main, summary_row

TINY = ["--scenes", "default", "--frames", "1", "--set", "shell.subdivision.levels=0"]


def test_summary_row_counts_failed_factorisations_and_reads_the_cpu_time():
    summary = {"run": {"shell": {"solver": {"method": "multigrid", "threads": 2}}},
               "frames": [{"frame": 1, "wall_time": 2.0, "cpu_time": 3.0,
                           "newton_iterations": 9, "details": {
                   "shell_iterations": 4, "shell_factorizations": 7, "shell_energy": 0.5,
                   "shell_converged": True}},
                          {"frame": 2, "wall_time": 1.0, "cpu_time": 1.5, "details": {
                              "shell_iterations": 2, "shell_factorizations": 2,
                              "shell_energy": 0.25, "shell_converged": False}}]}
    row = summary_row(summary)
    assert row["failed_factorizations"] == [3, 0]
    assert row["body_iterations"] == [9, 0]
    assert row["frames_cpu"] == 4.5 and row["frames_wall"] == 3.0
    assert row["unconverged"] == [2]
    assert (row["method"], row["threads"]) == ("multigrid", 2)
    del summary["frames"][0]["cpu_time"]  # code that does not record it
    assert summary_row(summary)["frames_cpu"] is None


def test_this_tree_and_head_run_the_same_tiny_frame(tmp_path):
    """A 165-vertex shell, one frame, with this tree and with HEAD in a worktree: both rows are
    there and converged, and the worktree is gone afterwards."""
    out = tmp_path / "product.json"
    doc = main([*TINY, "--before", "HEAD", "--out", str(out)])
    rows = {r["code"]: r for r in json.loads(out.read_text())["rows"]}
    assert doc["rows"] and set(rows) == {"this", "HEAD"}
    for row in rows.values():
        assert row["exit"] == 0, row.get("error")
        assert row["frames"] == 1 and row["unconverged"] == []
        assert row["method"] == "direct"  # 165 vertices: below the multigrid crossover
        assert sum(row["shell_iterations"]) > 0 and row["frames_wall"] > 0
    assert rows["this"]["frames_cpu"] > 0
    listed = subprocess.run(["git", "-C", str(REPO), "worktree", "list"], capture_output=True,
                            text=True, check=True).stdout
    assert "before-HEAD" not in listed
