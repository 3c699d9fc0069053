"""``benchmarks/iterative.py`` on the 10k warm-started frame: well-formed rows, same Newton."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from support import REPO


def test_warm_frame_rows_and_phase_space(tmp_path) -> None:
    """Direct, multigrid and multigrid + phase space reach the same minimiser in as many Newton
    iterations, solved twice by one solver (``--repeat 2``); the phase space halves the CG
    iterations (measured 111 -> 56)."""
    repo = REPO
    out = tmp_path / "iterative.json"
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               WRINKLES_CACHE=str(tmp_path / "cache"))
    proc = subprocess.run(
        [sys.executable, "benchmarks/iterative.py", "--sizes", "10k", "--hessian", "exact",
         "--to-tolerance", "1e-8", "--methods", "direct", "multigrid-fast-ew",
         "multigrid-phase-ew", "--repeat", "2", "--out", str(out)],
        cwd=repo, env=env, capture_output=True, text=True, timeout=900)
    print(proc.stdout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "cache" / "iterative").is_dir()  # not the repository's .cache
    rows = {r["method"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"direct", "multigrid-fast-ew", "multigrid-phase-ew"}
    for r in rows.values():
        assert r["reason"] == "gradient tolerance" and r["extra_iterations"] == 0
        assert r["energy_gap"] < 1e-12 and r["max_vertex_diff"] < 1e-8
        assert r["cpu_first"] > 0 and r["cpu_total"] > 0
    phase, plain = rows["multigrid-phase-ew"], rows["multigrid-fast-ew"]
    assert phase["true_residual_max"] < 0.2 and "indefinite_skips" in phase
    assert phase["cg_iterations"] < 0.7 * plain["cg_iterations"]
