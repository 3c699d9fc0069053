"""The scaling benchmark (issue 7 item 6) on tiny plates: fits, JSON and a solver cross-check.

``benchmarks/scaling.py`` times the set-up and two fixed-iteration frames of the wrinkling
plate per size and fits ``y ~ n^p`` on log-log. Here: the fit recovers a known exponent and
residual exactly, a tiny size solved with multigrid CG (fixed forcing 1e-8) reaches the direct
solve's energies, and the command line writes and appends well-formed JSON. No timing is
asserted.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.scaling import exponents, main, plate_vertices, run_one
from benchmarks.timing import power_fit

STAGES = {"hierarchy", "topology_rest", "clusters", "energy", "solver"}


def test_power_fit_recovers_exponent_residual_and_local_slopes():
    """log y = 1.25 log n + log 3 + d (1, -1, -1, 1) at log n = 0..3: the perturbation is
    orthogonal to (1, 1, 1, 1) and (0, 1, 2, 3), so p = 1.25 and c = log 3 exactly, every
    residual is +-d (RMS = max = d) and the local slopes are 1.25 - 2d, 1.25, 1.25 + 2d."""
    d = 0.1
    n = np.exp(np.arange(4.0))
    y = 3.0 * n**1.25 * np.exp(d * np.array([1.0, -1.0, -1.0, 1.0]))
    fit = power_fit(n, y)
    assert fit["p"] == pytest.approx(1.25, abs=1e-12)
    assert fit["c"] == pytest.approx(np.log(3.0), abs=1e-12)
    assert fit["rms_log_residual"] == pytest.approx(d, abs=1e-12)
    assert fit["max_log_residual"] == pytest.approx(d, abs=1e-12)
    assert fit["local"] == pytest.approx([1.25 - 2 * d, 1.25, 1.25 + 2 * d], abs=1e-12)


@pytest.fixture(scope="module")
def tiny_runs() -> dict[str, dict]:
    """One 289-vertex plate (8 x 8 cells, 1 level), 3 Newton iterations per frame, two ways."""
    return {m: run_one(1, 8, m, iterations=3, rtol=1e-14) for m in ("multigrid", "direct")}


def test_tiny_run_row_is_complete(tiny_runs):
    row = tiny_runs["multigrid"]
    assert row["n"] == plate_vertices(1, 8) == 17**2
    assert row["size"] == "L1x8" and row["clusters"] >= 1
    assert set(row["setup"]) == STAGES
    assert row["setup_cpu"] == pytest.approx(sum(v["cpu"] for v in row["setup"].values()))
    assert 0 < row["setup_peak_mib"] <= row["peak_mib"]
    for frame in row["frames"]:
        assert frame["iterations"] == 3 and frame["reason"] == "max_iterations"
        assert frame["cg_iterations"] >= 3 and frame["cg_fallbacks"] == 0
    assert all(f["cg_iterations"] == 0 for f in tiny_runs["direct"]["frames"])


def test_multigrid_frames_reach_the_direct_energies(tiny_runs):
    """CG to a true residual of 1e-8 follows the direct solve's Newton iterates. Measured
    after each 3-iteration frame: energies 1.2e-10 / 7.7e-8 relative apart, gradient norms
    3.6e-5 / 5.4e-5 (frame 1 is far from its minimum, ||g|| 2.0, so the inexact steps'
    differences show); bounds 1e-6 and 1e-3."""
    for mg, direct in zip(tiny_runs["multigrid"]["frames"], tiny_runs["direct"]["frames"],
                          strict=True):
        assert mg["energy"] == pytest.approx(direct["energy"], rel=1e-6)
        assert mg["grad_norm"] == pytest.approx(direct["grad_norm"], rel=1e-3)


def test_command_line_writes_and_appends_json(tmp_path):
    """Two tiny sizes in their own processes: rows sorted by n, two-point fits exact."""
    out = tmp_path / "scaling.json"
    common = ["--sizes", "2.5k", "--iterations", "2", "--method", "direct", "--out", str(out)]
    main([*common, "--base-cells", "8"])
    first = json.loads(out.read_text())
    assert [r["size"] for r in first["rows"]] == ["L1x8"]
    assert first["meta"]["exponents"] is None
    main([*common, "--base-cells", "6", "--append"])
    doc = json.loads(out.read_text())
    rows = doc["rows"]
    assert [r["n"] for r in rows] == [13**2, 17**2]
    fits = doc["meta"]["exponents"]
    assert fits == exponents(rows)
    peak = [r["peak_mib"] for r in rows]
    slope = np.log(peak[1] / peak[0]) / np.log(rows[1]["n"] / rows[0]["n"])
    assert fits["peak_mib"]["p"] == pytest.approx(slope, rel=1e-10)
    assert fits["peak_mib"]["rms_log_residual"] < 1e-12
    assert len(fits["frame1_cpu"]["local"]) == 1
    assert "frame1_cg_per_newton_iteration" not in fits  # direct: no CG, nothing to fit
