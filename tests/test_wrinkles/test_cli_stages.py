"""The frame loop's stage hook and ``wrinkles check`` (in process, serial)."""

from __future__ import annotations

import json

import pytest
from support import REPO

import wrinkles.cli as cli
from models.backend import MPI
from wrinkles.runner import make_record, prepare, run_frames
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


def test_a_frame_whose_shell_stopped_above_its_tolerance_says_so(tmp_path):
    """The default scene's first frame with ``shell.solver.max_iterations = 5``: the shell
    Newton stops above its tolerance, the frame is kept and its progress line says ``NOT
    converged`` with the gradient norm against the tolerance (as ``summary.json`` does)."""
    scene = with_frames(load_scene(REPO / "scenes" / "default.toml",
                                   ["output.render=false", "output.xdmf=false",
                                    "shell.solver.max_iterations=5"]), 1)
    lines: list[str] = []
    run = run_frames(prepare(scene, tmp_path, MPI.COMM_WORLD), lines.append)
    details = run.records[0].details
    assert details["shell_iterations"] == 5 and details["shell_converged"] is False
    assert details["shell_grad_norm"] > details["shell_tolerance"]
    expected = (f" NOT converged (|g| {details['shell_grad_norm']:.1e} > "
                f"{details['shell_tolerance']:.1e})")
    assert lines[0].split("  wall=")[0].endswith(expected), lines[0]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"][0]["details"]["shell_converged"] is False
    main = {"time": 0.25, "newton_iterations": 3, "energy": 1.0, "min_det_f": 0.9}
    done = make_record(1, {**main, **details, "shell_converged": True}, {}, 1.0)
    assert "NOT converged" not in done.progress_line(1, static=True)


def test_a_frame_whose_shell_passes_through_itself_says_so(tmp_path):
    """The default scene's first frame has no self-intersection (``shell_self_intersections``
    0 in ``summary.json``, nothing in its line); with one skin vertex pushed through the bar
    and out of its far side the faces around it cross the far side's faces, and the progress
    line says ``SELF-INTERSECTING`` with their count."""
    import numpy as np

    from models.shell.self_intersection import intersecting_faces

    scene = with_frames(load_scene(REPO / "scenes" / "default.toml",
                                   ["output.render=false", "output.xdmf=false"]), 1)
    lines: list[str] = []
    run = run_frames(prepare(scene, tmp_path, MPI.COMM_WORLD), lines.append)
    details = run.records[0].details
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"][0]["details"]["shell_self_intersections"] == 0
    assert "SELF-INTERSECTING" not in lines[0]
    shell = run.shell
    assert shell is not None
    x = shell.x.copy()
    top = int(np.argmax(x[:, 2]))
    x[top, 2] = 2 * x[:, 2].min() - x[top, 2]  # mirrored below the bar's bottom
    pairs = len(intersecting_faces(x, shell.topology.faces))
    assert pairs >= 6  # each face around the vertex crosses the bottom at least once
    record = make_record(1, {"time": 0.25, "newton_iterations": 3, "energy": 1.0,
                             "min_det_f": 0.9, **details, "shell_self_intersections": pairs},
                         {}, 1.0)
    assert f"SELF-INTERSECTING ({pairs} face pairs)" in record.progress_line(1, static=True)
