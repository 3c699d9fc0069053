"""A skin compressed until its wrinkles fold: hinges closing past flat-on-flat.

``scenes/default.toml`` taken beyond its four frames (10 % compression) as a user does with
``--frames 7``: at 17.5 % a wrinkle near the moving clamp folds shut. Before the hinge angles
were followed from solve to solve (docs/notes/hinge-branches.md) frame 7 stopped with "no
progress" on a hinge at exactly pi, the jump of ``theta`` in ``(-pi, pi]``.
"""

from __future__ import annotations

import numpy as np
from support import REPO

from models.backend import MPI
from models.shell.hinge_angle import hinge_angles, on_branch
from wrinkles.runner import prepare, run_frame
from wrinkles.scene import load_scene, with_frames


def test_the_compressed_bar_converges_through_a_fold_closing_past_pi(tmp_path):
    scene = with_frames(load_scene(REPO / "scenes" / "default.toml",
                                   ["output.render=false", "output.xdmf=false"]), 7)
    run = prepare(scene, tmp_path / "out", MPI.COMM_SELF)
    for frame in range(1, run.n_frames + 1):
        run.records.append(run_frame(run, frame))
    shell = run.shell
    assert shell is not None
    assert all(r.details["shell_converged"] for r in run.records)
    branch = shell.energy.hinge_branch
    assert branch is not None
    followed = on_branch(hinge_angles(shell.x, shell.topology.hinges), branch)
    print("iterations", [r.details["shell_iterations"] for r in run.records],
          "largest followed hinge angle", float(np.abs(followed).max()))
    assert np.abs(followed).max() > np.pi  # measured 3.42 rad: the fold closed past pi
    assert np.isfinite(run.records[-1].details["shell_energy"])
