"""The frame loop's stage hook and ``wrinkles check`` (in process, serial)."""

from __future__ import annotations

import json

import pytest
from support import REPO

import wrinkles.cli as cli
from models.backend import MPI
from wrinkles.runner import prepare, run_frames
from wrinkles.scene import load_scene, scene_dict, scene_from_dict, with_frames

DEFAULT = REPO / "scenes" / "drop_block.toml"  # the falling block (default.toml: wrinkles)


def test_extra_stage_runs_after_the_body_and_lands_in_the_summary(tmp_path):
    run = prepare(with_frames(load_scene(DEFAULT), 3), tmp_path, MPI.COMM_WORLD)
    seen: list[tuple[int, float]] = []

    def shell_stage(frame: int) -> dict[str, float]:
        seen.append((frame, run.body.t))
        return {"shell_energy": 10.0 * frame}

    run.stages.append(("shell", shell_stage))
    lines: list[str] = []
    run_frames(run, lines.append)
    assert [f for f, _ in seen] == [1, 2, 3]
    assert [t for _, t in seen] == pytest.approx([0.01, 0.02, 0.03], abs=1e-15)  # body first
    assert len(lines) == 3 and lines[-1].startswith("frame    3/3")
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert [r["details"]["shell_energy"] for r in summary["frames"]] == [10.0, 20.0, 30.0]
    assert all(set(r["stage_times"]) == {"body", "shell"} for r in summary["frames"])
    assert summary["run"]["status"] == "completed"
    assert summary["run"]["mesh"]["dofs"] == 3 * summary["run"]["mesh"]["vertices"]  # P1


def test_check_prints_the_resolved_scene(capsys):
    assert cli.main(["check", str(DEFAULT), "--set", "material.E=7e4"]) == 0
    data = json.loads(capsys.readouterr().out)["scene"]
    assert data["material"]["E"] == 7.0e4
    scene = scene_from_dict(data, REPO)
    assert scene_dict(scene) == data
    assert scene.body.contacts[0].normal == (0.0, 0.0, 1.0)


def test_check_refuses_bad_scene(capsys):
    assert cli.main(["check", str(DEFAULT), "--set", "material.nu=0.5"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("error: drop_block.toml: material.nu must be < 0.5")
