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
    """``scenes/wrinkle_skin.toml --frames 12`` (48 %): the bar buckles as a column, frame 11
    stops at its iteration cap with folds carried through themselves, and frame 12's warm
    start pulled such a fold back onto a target bent the other way (measured: vertex 33). That
    start used to end the run with exit 2; now the hinge takes the target's branch
    (``ShellEnergy.release_folds``), frame 12 converges and says that its skin passes through
    itself. Measured: frame 11 58 face pairs, frame 12 140 iterations, 87 vertices repaired,
    125 pairs."""
    scene = with_frames(load_scene(REPO / "scenes" / "wrinkle_skin.toml",
                                   ["output.render=false", "output.xdmf=false"]), 12)
    run = run_frames(prepare(scene, tmp_path / "out", MPI.COMM_SELF), lambda line: None)
    last = run.records[-1].details
    print({k: last[k] for k in ("shell_iterations", "shell_start_repaired",
                                "shell_self_intersections")})
    assert len(run.records) == 12 and last["shell_converged"]
    assert last["shell_start_repaired"] > 0
    assert last["shell_self_intersections"] > 0  # no contact between faces sharing no hinge
