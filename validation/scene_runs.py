"""The twisted-cylinder and bent-bar scenes from the CLI, and their wrinkle metrics.

Wrinkle amplitude of a face: the standard deviation over the face of the shell's offset from
its embedded target along the target's unit normal, ``d_i = (x_i - y_i) . n_y,i`` (``x`` and
``y = B (X_q + u_q)`` from the run's checkpoint). The face mean is taken out: a stretched
membrane over a convex face sinks uniformly towards the centre of curvature, a smooth offset
that is not a wrinkle. Used by ``tests/test_scenes_extra.py`` and ``paper/scripts/scenes.py``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from models.shell.rest import vertex_normals
from wrinkles.checkpoint import CHECKPOINT_NAME, read_state
from wrinkles.shell_output import SHELL_XDMF_NAME, read_shell_series

BAR_LENGTH, BAR_SIDE = 0.3, 0.05
CYL_RADIUS, CYL_LENGTH, CYL_TWIST_RATE = 0.04, 0.24, 1.0


REPO = Path(__file__).resolve().parents[1]


COARSE = ("--frames", "2", "--set", "body.dt=0.5", "--set", "shell.subdivision.levels=1",
          "--set", "output.render=false")
"""Coarse test settings: the full bend / twist in 2 frames, one subdivision level."""


def wrinkles_cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """Run ``python -m wrinkles ARGS`` in a subprocess from the repository (one BLAS thread).

    A serial command: a large one-way shell goes on to the machine's cores as MPI ranks, as
    for a user (:func:`solvers.solver_choice.choose_ranks`).
    """
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "wrinkles", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=REPO, env=env)


def run_scene(scene: str, out: Path, *extra: str,
              timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """Run ``python -m wrinkles run scenes/<scene>.toml --out OUT --overwrite EXTRA`` (serial)."""
    return wrinkles_cli("run", str(REPO / "scenes" / f"{scene}.toml"), "--out", str(out),
                        "--overwrite", *extra, timeout=timeout)


def normal_offsets(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions of the shell and its normal offsets ``d`` from the target (last frame)."""
    rest, faces, _, _ = read_shell_series(out / SHELL_XDMF_NAME)
    shell = read_state(out / CHECKPOINT_NAME).arrays["shell"]
    x, y = shell["positions"], shell["target"]
    return rest, np.einsum("ij,ij->i", x - y, vertex_normals(y, faces))


def amplitude(d: np.ndarray, mask: np.ndarray) -> float:
    """Wrinkle amplitude of a face: std of the normal offsets over it (mean removed) [m]."""
    return float(np.std(d[mask]))


def bar_faces(rest: np.ndarray, length: float = BAR_LENGTH,
              side: float = BAR_SIDE) -> dict[str, np.ndarray]:
    """Masks of the bent bar's faces z = 0 and z = side, middle 2/3 of the length.

    The ends turn about y with angular velocity -+0.5: the face z = 0 is the concave
    (compressed) side, z = side the convex (stretched) side.
    """
    middle = np.abs(rest[:, 0] - length / 2) < length / 3
    return {"compressed": middle & (np.abs(rest[:, 2]) < 1e-6),
            "stretched": middle & (np.abs(rest[:, 2] - side) < 1e-6)}


def bent_bar_metrics(out: Path) -> dict[str, float]:
    """Wrinkle amplitudes of the compressed and stretched faces and their ratio."""
    rest, d = normal_offsets(out)
    faces = bar_faces(rest)
    amp = {name: amplitude(d, mask) for name, mask in faces.items()}
    return {"amplitude_compressed": amp["compressed"], "amplitude_stretched": amp["stretched"],
            "amplitude_ratio": amp["compressed"] / amp["stretched"],
            "mean_offset_stretched": float(np.mean(d[faces["stretched"]]))}


def end_rotation(out: Path, x_end: float) -> np.ndarray:
    """Rotation angle about the x axis of each body node of the face ``x = x_end`` [rad].

    ``atan2((a x b)_x, a . b)`` of the node's arm ``a = (y, z)`` before and ``b`` after the
    deformation; nodes within R/4 of the axis are left out (short arms).
    """
    state = read_state(out / CHECKPOINT_NAME)
    X, u = state.coords, state.fields["displacement"].reshape(-1, 3)
    face = (np.abs(X[:, 0] - x_end) < 1e-6) & (np.hypot(X[:, 1], X[:, 2]) > CYL_RADIUS / 4)
    a, b = X[face, 1:], (X + u)[face, 1:]
    return np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.einsum("ij,ij->i", a, b))


def twisted_cylinder_metrics(out: Path) -> dict[str, float]:
    """End rotation (mean, spread) and the lateral surface's wrinkle amplitude / radius."""
    angles = end_rotation(out, CYL_LENGTH)
    rest, d = normal_offsets(out)
    lateral = ((np.hypot(rest[:, 1], rest[:, 2]) > 0.9 * CYL_RADIUS)
               & (np.abs(rest[:, 0] - CYL_LENGTH / 2) < 0.4 * CYL_LENGTH))
    amp = amplitude(d, lateral)
    return {"end_angle": float(np.mean(angles)), "end_angle_spread": float(np.ptp(angles)),
            "amplitude": amp, "amplitude_over_radius": amp / CYL_RADIUS}
