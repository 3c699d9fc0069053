"""benchmarks/cli_start.py times the commands that run no frame, on a run it makes first."""

from __future__ import annotations

import json
import subprocess
import sys

from benchmarks.cli_start import REPO


def test_every_command_is_timed_on_a_run_of_one_frame(tmp_path):
    out = tmp_path / "cli.json"
    done = subprocess.run([sys.executable, "benchmarks/cli_start.py", "--repeat", "1",
                           "--out", str(out)], cwd=REPO, capture_output=True, text=True,
                          timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    doc = json.loads(out.read_text())
    assert doc["before"] is None and doc["repeat"] == 1
    times = doc["times"]["this"]
    assert sorted(times) == ["--help", "check", "plot", "render", "view"]
    assert all(len(t) == 1 and 0.0 < t[0] < 600.0 for t in times.values())
    assert "median s" in done.stdout and str(out) in done.stdout
