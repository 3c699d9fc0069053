"""The speed/accuracy benchmark in quick mode (issue 7 "Checks"): well-formed JSON, and the
error against the reference decreases as the subdivision level increases, other settings fixed.

Also unit checks of its comparison helpers: barycentric interpolation reproduces a linear
field exactly, and the Pareto front keeps exactly the non-dominated rows.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import REPO, load_script

from benchmarks.speed_accuracy import (
    GROUP_ORDER,
    SceneFacts,
    barycentric_interpolate,
    pareto,
    sweep,
)

ROW_KEYS = {"name", "group", "overrides", "time_per_frame", "frame_times", "peak_rss_mib",
            "vertices", "rms", "max", "rms_rel", "bending_energy_rel_error", "wavelength",
            "shell_iterations", "matched", "frame_cpu_times", "cpu_per_frame",
            "body_iterations", "load_avg_1min", "key"}


def run_quick(out: Path, *flags: str) -> subprocess.CompletedProcess:
    """``speed_accuracy.py --quick --out OUT FLAGS`` in a subprocess (exit code checked)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "benchmarks/speed_accuracy.py", "--quick", "--out",
                           str(out), *flags], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def quick(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("speed") / "speed_accuracy.json"
    print(run_quick(out, "--only", "subdivision").stdout)
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
        assert len(row["frame_cpu_times"]) == 2 and min(row["frame_cpu_times"]) > 0
        assert row["cpu_per_frame"] == pytest.approx(np.mean(row["frame_cpu_times"]))
        assert 0 <= row["rms"] <= row["max"]
        assert row["matched"] == "common_vertices"  # same body mesh: nested shells
    assert set(doc["pareto"]) <= set(names) and doc["pareto"]
    assert set(doc["pareto_bending"]) <= set(names) and doc["pareto_bending"]
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
    for r, eb in zip(rows, (0.5, 0.6, 0.1, 0.2, 0.9, 0.05, None, 0.0), strict=True):
        r["bending_energy_rel_error"] = eb  # g unmeasured, h unconverged
    assert [r["name"] for r in pareto(rows, "bending_energy_rel_error")] == ["e", "a", "c",
                                                                             "f"]


def test_resume_reuses_stored_rows_and_budget_stops_new_ones(quick):
    """--resume keeps every stored row bit for bit; --budget 0 starts no new configuration."""
    before = {r["name"]: r for r in quick["doc"]["rows"]}
    proc = run_quick(quick["out"], "--only", "subdivision", "hessian", "--resume",
                     "--budget", "0")
    doc = json.loads(quick["out"].read_text())
    after = {r["name"]: r for r in doc["rows"]}
    assert after == before  # same rows, same measured times: nothing was rerun
    assert doc["notes"]["not_run"] == ["hessian=gauss_newton", "hessian=mixed"]
    assert "rerun with --resume" in proc.stdout


FACTS = SceneFacts(levels=2, hessian="exact", far_hessian="", rtol=1e-6, h=0.02,
                   dynamic=False, dt=0.25, steps_per_frame=1, frames=4)


def overrides_of(configs, name: str) -> dict[str, str]:
    """``key -> value`` of the overrides of the configuration ``name``."""
    (config,) = [c for c in configs if c.name == name]
    return dict(o.split("=", 1) for o in config.overrides)


def test_sweep_drops_duplicates_of_base_and_runs_in_group_order():
    configs = sweep([0, 1, 2, 3], FACTS, None)
    names = [c.name for c in configs]
    assert len(names) == len(set(names)) and names[0] == "base"
    assert "levels=2" not in names and "hessian=exact" not in names  # = base
    assert {"levels=0", "levels=1", "levels=3", "hessian=mixed"} <= set(names)
    combos = [n for n in names if n.startswith("L")]  # at the scene's level, GN finer
    assert combos == ["L2+gauss_newton+rtol=0.001", "L2+mixed+rtol=0.001",
                      "L2+projected+rtol=0.001", "L3+gauss_newton+rtol=0.001"]
    assert not {"hessian=projected", "max_it=10", "linear=superlu_dist"} & set(names)
    ranks = [GROUP_ORDER.index(c.group) for c in configs]
    assert ranks == sorted(ranks)
    assert [c.name for c in sweep([0], FACTS, ["newton_cap"])] == ["base", "max_it=10",
                                                                     "max_it=30"]
    mixed = dataclasses.replace(FACTS, far_hessian="projected")
    assert "hessian=exact" in [c.name for c in sweep([0], mixed, ["hessian"])]


def test_time_knobs_keep_the_final_load_and_the_frame_interval():
    static = sweep([0], FACTS, ["time"])[1:]
    for config in static:  # frames x load per frame = 1, the scene's final load
        o = overrides_of(static, config.name)
        assert int(o["time.frames"]) * float(o["body.dt"]) == pytest.approx(1.0, rel=1e-15)
    dynamic = dataclasses.replace(FACTS, dynamic=True, dt=0.005, steps_per_frame=2)
    steps = sweep([0], dynamic, ["time"])[1:]
    assert [c.name for c in steps] == ["steps_per_frame=1", "steps_per_frame=4"]
    for config in steps:  # steps x dt = the scene's frame interval 0.01 s
        o = overrides_of(steps, config.name)
        assert int(o["time.steps_per_frame"]) * float(o["body.dt"]) == pytest.approx(
            0.01, rel=1e-15)
    body = sweep([0, 3], dynamic, ["body"],
                 ref_extra=["time.steps_per_frame=4", "body.dt=0.0025"])
    assert [c.name for c in body] == ["base", "body=P2", "body=reference",
                                      "L0+body=reference"]
    assert overrides_of(body, "body=reference") == {"body.degree": "2", "body.dt": "0.0025",
                                                    "time.steps_per_frame": "4"}
    assert [c.name for c in sweep([0], FACTS, ["body"])] == ["base", "body=P2"]
    mesh = sweep([0], FACTS, ["mesh"])[1:]
    assert [c.name for c in mesh] == ["h=0.03", "h=0.04"]


def test_paper_renders_the_pareto_and_preset_rows_of_the_json(quick, tmp_path):
    """paper/make_paper.py's speed/accuracy block: the JSON's front and presets, its numbers."""
    load_script(REPO / "paper" / "steps.py")  # imported by make_paper from beside it
    make_paper = load_script(REPO / "paper" / "make_paper.py")

    doc = json.loads(quick["out"].read_text())
    doc["presets"] = {"preview": "levels=1", "balanced": "base", "final": "reference"}
    path = tmp_path / "speed_accuracy.json"
    text = make_paper.speed_accuracy_part(doc, path)
    assert text.count("Table: ") == 3 and doc["pareto"] and doc["pareto_bending"]
    for row in (r for r in doc["rows"] if r["name"] in doc["pareto"]):
        line = f"| {row['name']} | {row['vertices']} | 2 | {make_paper.fmt(row['time_per_frame'])}"
        assert line + f" | {make_paper.fmt(row['cpu_per_frame'])} |" in text
    ref = doc["reference"]
    assert (f"| final (reference) | {ref['vertices']} | 2 | {make_paper.fmt(ref['time_per_frame'])}"
            in text)
    assert "| balanced (base) |" in text and "| preview (levels=1) |" in text
    assert "left out: hessian=projected" in text
