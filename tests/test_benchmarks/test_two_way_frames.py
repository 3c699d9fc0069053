"""benchmarks/two_way.py: one-way and two-way frames side by side, the skin's effect."""

from __future__ import annotations

import json

import numpy as np

from benchmarks.two_way import effect, main, rms


def test_effect_measures_body_and_shell_differences():
    """``body_rms_rel`` is the RMS nodal difference over the one-way RMS displacement."""
    one = {"body_u": np.array([3.0, 0.0, 0.0, 0.0, 4.0, 0.0]), "elastic": [2.0],
           "shell": {"rest": np.zeros((2, 3)), "x": np.array([[1.0, 0, 0], [0, 1.0, 0]]),
                     "target": np.zeros((2, 3)), "faces": np.zeros((0, 3), dtype=int)}}
    two = {"body_u": np.array([3.0, 0.0, 1.0, 0.0, 4.0, 1.0]), "elastic": [3.0],
           "shell": {**one["shell"], "x": np.array([[1.0, 0, 1.0], [0, 1.0, 0]])}}
    out = effect(one, two)
    assert rms(np.array([[3.0, 0, 0], [0, 4.0, 0]])) == np.sqrt(12.5)
    assert out["body_rms_rel"] == 1.0 / np.sqrt(12.5)
    assert out["elastic_ratio"] == [1.5]
    assert out["shell_rms_rel"] == np.sqrt(0.5)


def test_tiny_frames_of_both_scenes(tmp_path):
    """One frame of both scenes at 0 subdivision levels: both converge, the two-way run is
    timed against the one-way run, and the skin changes the body and stiffens it."""
    out = tmp_path / "two_way.json"
    main(["--frames", "1", "--set", "shell.subdivision.levels=0", "--out", str(out)])
    doc = json.loads(out.read_text())
    one, two = doc["rows"]["one_way"], doc["rows"]["two_way"]
    assert all(one["converged"]) and all(two["converged"])
    assert two["coupling_iterations"][0] >= 1 and two["linear_seconds_per_iteration"] > 0
    assert 0.0 < two["effect"]["body_rms_rel"] < 0.5
    assert two["effect"]["elastic_ratio"][0] > 1.0
    assert "two_way" in doc["table"]
