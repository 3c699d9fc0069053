"""benchmarks/product_frames.py runs the CLI of this tree and of a git revision side by side."""

from __future__ import annotations

import json
import subprocess

import pytest

from benchmarks.product_frames import HEADER, REPO, main, print_row, spread_table, summary_row

TINY = ["--scenes", "default", "--frames", "1", "--set", "shell.subdivision.levels=0"]


def test_summary_row_counts_failed_factorisations_and_reads_the_cpu_time():
    summary = {"run": {"shell": {"solver": {"method": "multigrid", "threads": 2}}},
               "frames": [{"frame": 1, "wall_time": 2.0, "cpu_time": 3.0,
                           "newton_iterations": 9, "details": {
                   "shell_iterations": 4, "shell_factorizations": 7, "shell_energy": 0.5,
                   "shell_converged": True, "shell_self_intersections": 3}},
                          {"frame": 2, "wall_time": 1.0, "cpu_time": 1.5, "details": {
                              "shell_iterations": 2, "shell_factorizations": 2,
                              "shell_energy": 0.25, "shell_converged": False}}]}
    row = summary_row(summary)
    assert row["failed_factorizations"] == [3, 0]
    assert row["body_iterations"] == [9, 0]
    assert row["frames_cpu"] == 4.5 and row["frames_wall"] == 3.0
    assert row["unconverged"] == [2]
    assert row["self_intersections"] == [3, None]  # the second frame's code counted none
    assert (row["method"], row["threads"]) == ("multigrid", 2)
    del summary["frames"][0]["cpu_time"]  # code that does not record it
    assert summary_row(summary)["frames_cpu"] is None


@pytest.mark.slow  # 60-75 s in CI (HEAD's worktree compiles its numba kernels afresh): the suite's
# slowest case, with the suite at 25-28 of its 30 minutes on 2 cores
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
        assert row["process_wall"] > row["frames_wall"]  # the command: set-up and output too
    assert rows["this"]["frames_cpu"] > 0
    listed = subprocess.run(["git", "-C", str(REPO), "worktree", "list"], capture_output=True,
                            text=True, check=True).stdout
    assert "before-HEAD" not in listed


def test_the_spread_table_gives_mean_min_and_max_over_the_seeds_and_counts_failed_runs():
    def row(seed: int, its: list[int], facts: list[int], cpu: float, energy: float,
            exit_code: int = 0) -> dict:
        return {"scene": "default", "code": "this", "ranks": 1, "seed": seed, "exit": exit_code,
                "shell_iterations": its, "factorizations": facts,
                "failed_factorizations": [f - i for f, i in zip(facts, its, strict=True)],
                "frames_cpu": cpu, "frames_wall": cpu + 1.0, "shell_energy": [0.1, energy]}

    rows = [row(0, [10, 20], [15, 20], 2.0, 0.5), row(1, [30, 10], [30, 20], 4.0, 0.7),
            row(2, [1, 1], [1, 1], 9.0, 9.0, exit_code=2)]
    (entry,) = spread_table(rows)
    assert (entry["runs"], entry["failed_runs"]) == (2, 1)
    assert entry["shell_iterations"] == {"mean": 35.0, "sd": 5.0, "min": 30, "max": 40}
    assert entry["frames_time"]["mean"] == 3.0 and entry["frames_time"]["sd"] == 1.0
    assert entry["final_energy"]["min"] == 0.5 and entry["final_energy"]["max"] == 0.7
    assert entry["failed_percent"]["mean"] == (100 * 5 / 35 + 100 * 10 / 50) / 2


def test_a_serial_command_that_went_on_two_ranks_is_timed_by_its_wall():
    """A large shell's serial command relaunches on the cores: its CPU is rank 0's only."""
    rows = [{"scene": "bunny_drop", "code": "this", "ranks": 1, "run_ranks": 2, "seed": 0,
             "exit": 0, "shell_iterations": [5], "factorizations": [5],
             "failed_factorizations": [0], "frames_cpu": 3.0, "frames_wall": 4.0,
             "shell_energy": [1.0]}]
    (entry,) = spread_table(rows)
    assert entry["ranks"] == 2 and entry["frames_time"]["mean"] == 4.0
    rows[0]["run_ranks"] = 1
    (entry,) = spread_table(rows)
    assert entry["ranks"] == 1 and entry["frames_time"]["mean"] == 3.0


def test_a_row_shows_the_whole_command_wall_under_its_header(capsys):
    """``cmd s`` is the command's wall (launch, set-up, output), beside the frames' wall."""
    summary = {"run": {"shell": {"solver": {"method": "multigrid", "threads": 1}}},
               "frames": [{"frame": 1, "wall_time": 2.5, "cpu_time": 2.25, "details": {
                   "shell_iterations": 4, "shell_factorizations": 5, "shell_energy": 0.5,
                   "shell_converged": True, "shell_self_intersections": 0}}]}
    row = {"exit": 0, "ranks": 1, "process_wall": 7.75, "process_cpu": 7.5} | summary_row(summary)
    print_row("default", "this", row)
    cells = dict(zip(HEADER.replace("cmd s", "cmd_s").replace("frames s", "frames_s")
                     .replace("s/frame", "s_frame").replace("wall s", "wall_s")
                     .replace("mem MB", "mem_MB").replace("proc CPU", "proc_CPU")
                     .replace("final W", "final_W").split(),
                     capsys.readouterr().out.split(), strict=False))
    assert cells["cmd_s"] == "7.75" and cells["wall_s"] == "2.50" and cells["proc_CPU"] == "7.50"


def test_the_spread_of_a_scene_without_a_shell_has_times_and_no_energy():
    rows = [{"scene": "drop_block", "code": "this", "ranks": 1, "seed": seed, "exit": 0,
             "shell_iterations": [0, 0], "factorizations": [0, 0],
             "failed_factorizations": [0, 0], "frames_cpu": cpu, "frames_wall": cpu,
             "shell_energy": [None, None]} for seed, cpu in ((0, 0.4), (1, 0.6))]
    (entry,) = spread_table(rows)
    assert entry["frames_time"]["mean"] == 0.5
    assert entry["final_energy"] == {"mean": None, "sd": None, "min": None, "max": None}


def test_a_before_that_names_no_commit_is_refused_by_name():
    with pytest.raises(SystemExit, match=r"--before no-such-rev: no such commit"):
        main(["--before", "no-such-rev", "--scenes", "default"])
