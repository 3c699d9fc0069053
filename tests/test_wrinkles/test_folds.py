"""A skin compressed until its wrinkles fold: hinges closing to flat-on-flat.

``scenes/default.toml`` taken beyond its four frames (10 % compression) as a user does with
``--frames 8``: at 17.5 % (frame 7) a wrinkle near the moving clamp folds shut. Before the
hinge angles were followed from solve to solve, frame 7 stopped with "no progress" on a hinge
at exactly pi, the jump of ``theta`` in ``(-pi, pi]``; with the angles followed but no fold
contact the fold closed 0.28 rad through itself; now the fold contact holds it at its faces
touching (docs/notes/hinge-branches.md).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from support import REPO

from models.backend import MPI
from models.shell.hinge_angle import hinge_angles, on_branch
from wrinkles.runner import prepare, run_frame, run_frames, save_frame
from wrinkles.scene import load_scene, with_frames


def test_the_compressed_bar_folds_shut_converges_and_resumes_on_the_fold(tmp_path):
    """Frames 1-8 converge; after frame 7 a fold is held shut at its faces touching (its
    followed angle within the contact gap of pi, not past it); a run resumed from frame 7's
    checkpoint (which carries the hinges' references) takes frame 8 to the same shell as the
    straight run, within the solver's tolerance."""
    scene = with_frames(load_scene(REPO / "scenes" / "default.toml",
                                   ["output.render=false", "output.xdmf=false"]), 8)
    run = prepare(scene, tmp_path / "straight", MPI.COMM_SELF)
    shell = run.shell
    assert shell is not None
    for frame in range(1, 8):
        run.records.append(run_frame(run, frame))
        save_frame(run, frame)
    branch = shell.energy.hinge_branch
    assert branch is not None
    followed = on_branch(hinge_angles(shell.x, shell.topology.hinges), branch)
    print("iterations", [r.details["shell_iterations"] for r in run.records],
          "largest followed hinge angle", float(np.abs(followed).max()))
    gap = shell.params.fold_gap
    # measured 3.141 rad (3.42 without the contact, the fold through itself)
    assert np.pi - gap < np.abs(followed).max() < np.pi
    shutil.copytree(tmp_path / "straight", tmp_path / "resumed")
    run.records.append(run_frame(run, 8))
    assert all(r.details["shell_converged"] for r in run.records)
    resumed = run_frames(prepare(scene, tmp_path / "resumed", MPI.COMM_SELF, restart=True),
                         lambda line: None)
    assert resumed.shell is not None and len(resumed.records) == 8
    assert resumed.records[-1].details["shell_converged"]
    apart = float(np.abs(resumed.shell.x - shell.x).max())
    print(f"frame 8, resumed against straight: max |dx| = {apart:.2e} m")
    # the multigrid path resumes to the solver's tolerance, not bit for bit
    assert apart < 1e-5


@pytest.mark.slow
def test_a_bar_buckled_as_a_column_runs_to_its_last_frame(tmp_path):
    """``scenes/wrinkle_skin.toml --frames 12`` (48 %): the bar buckles as a column. The run
    used to end with exit 2 at frame 12's warm start (frame 11 at its 400-iteration cap left
    a fold shut against a target bent the other way); with that fold released
    (``ShellEnergy.release_folds``) frame 12 converged, frame 11 still at its cap; with the
    warm start turned with the target (``wrinkles.shell_stage.carried_start``) every frame
    converges and no release is needed. Measured: 938 iterations, frames 11-12 127 / 60, their
    skin passing through itself in 74 / 71 face pairs (no contact between faces that share
    no hinge)."""
    scene = with_frames(load_scene(REPO / "scenes" / "wrinkle_skin.toml",
                                   ["output.render=false", "output.xdmf=false"]), 12)
    run = run_frames(prepare(scene, tmp_path / "out", MPI.COMM_SELF), lambda line: None)
    records = [r.details for r in run.records]
    print("iterations", [r["shell_iterations"] for r in records],
          "intersecting pairs", [r["shell_self_intersections"] for r in records])
    assert len(records) == 12 and all(r["shell_converged"] for r in records)
    assert records[-1]["shell_self_intersections"] > 0
