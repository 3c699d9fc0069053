"""The speed/accuracy benchmark in quick mode (issue 7 "Checks"): well-formed JSON, and the
error against the reference decreases as the subdivision level increases, other settings fixed.

Also unit checks of its comparison helpers: barycentric interpolation reproduces a linear
field exactly, and the Pareto front keeps exactly the non-dominated rows.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from speed_accuracy import barycentric_interpolate, pareto  # noqa: E402

ROW_KEYS = {"name", "group", "overrides", "time_per_frame", "frame_times", "peak_rss_mib",
            "vertices", "rms", "max", "rms_rel", "bending_energy_rel_error", "wavelength",
            "shell_iterations", "matched"}


@pytest.fixture(scope="module")
def quick(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("speed") / "speed_accuracy.json"
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "benchmarks/speed_accuracy.py", "--quick", "--only",
                           "subdivision", "--out", str(out)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    print(proc.stdout)
    return {"doc": json.loads(out.read_text()), "out": out}


def test_quick_json_is_well_formed(quick):
    doc, out = quick["doc"], quick["out"]
    assert doc["quick"] is True and doc["reference"]["levels"] == 2
    names = [r["name"] for r in doc["rows"]]
    assert names == ["base", "levels=0", "levels=1"]
    for row in doc["rows"]:
        assert "error" not in row, row.get("error")
        assert ROW_KEYS <= set(row), ROW_KEYS - set(row)
        assert row["time_per_frame"] > 0 and row["peak_rss_mib"] > 0
        assert len(row["frame_times"]) == 2 and np.isfinite(row["rms_rel"])
        assert 0 <= row["rms"] <= row["max"]
        assert row["matched"] == "common_vertices"  # same body mesh: nested shells
    assert set(doc["pareto"]) <= set(names) and doc["pareto"]
    assert out.with_suffix(".png").stat().st_size > 1000
    assert out.with_name(out.stem + "_pareto.md").read_text().startswith("| setting")


def test_error_decreases_with_subdivision(quick):
    rows = {r["name"]: r for r in quick["doc"]["rows"]}
    levels = [rows["levels=0"], rows["levels=1"], rows["base"]]  # base: the scene's 2 levels
    assert [r["vertices"] for r in levels] == sorted(r["vertices"] for r in levels)
    errors = [r["rms_rel"] for r in levels]
    print("rms_rel by level 0, 1, 2:", errors)
    assert errors[0] > errors[1] > errors[2]


def test_barycentric_interpolation_reproduces_linear_fields(rng):
    rest = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    values = rest @ np.array([[1.0, 2.0, -1.0], [0.5, -3.0, 2.0], [0.0, 0.0, 0.0]])
    points = np.column_stack([rng.random((50, 2)), np.zeros(50)])
    got = barycentric_interpolate(rest, faces, values, points)
    np.testing.assert_allclose(got, points @ np.array([[1.0, 2.0, -1.0], [0.5, -3.0, 2.0],
                                                       [0.0, 0.0, 0.0]]), atol=1e-13)


def test_pareto_keeps_the_non_dominated_rows():
    rows = [{"name": n, "frame_times": [t / 2, t / 2], "rms_rel": e} for n, t, e in
            [("a", 1.0, 0.5), ("b", 2.0, 0.2), ("c", 2.5, 0.3), ("d", 3.0, 0.1), ("e", 0.5, 0.9),
             ("f", 4.0, 0.1), ("g", 3.5, 0.0995)]]
    rows.append({"name": "h", "frame_times": [0.1], "rms_rel": 0.01, "shell_converged": [False]})
    # g improves on d by only 0.5 % (< PARETO_MARGIN); h stopped unconverged
    assert [r["name"] for r in pareto(rows)] == ["e", "a", "b", "d"]
