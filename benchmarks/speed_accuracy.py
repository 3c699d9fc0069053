"""The speed/accuracy trade of a wrinkle scene: sweep the knobs, time them, compare to a reference.

A *reference* run of the scene (default ``scenes/default.toml``) is made once with the
finest settings that fit (``--ref-levels`` subdivision levels, exact Hessian, shell Newton
``rtol = 1e-8``, P2 body) and stored under ``benchmarks/results/`` as
``speed_accuracy_reference_<scene>[_quick].npz`` (regenerated when missing or when its
settings changed; not committed). Then every configuration of the sweep (one knob at a time
from the scene's own settings, plus a few combinations) runs the same frames and is compared
with the reference at the final frame:

* shell position error, RMS and max over the compared points [m], and the RMS relative to
  the RMS displacement of the reference shell (``rms_rel``, the Pareto axis). Shells on the
  same body mesh share their first vertices (linear and Loop subdivision keep the coarse
  vertices first and the vertex order of every level), so a coarser shell is compared on
  its own vertices (common vertices); a shell on another body mesh is interpolated
  (barycentric, nearest rest triangle) at the reference's rest points;
* bending energy ``k_B W_B`` relative error;
* dominant wrinkle wavelength (:func:`validation.measure.shell_wavelength` of the normal
  deviation from the target on the lateral faces along the longest axis) and its relative
  error;
* wall time per frame AND process CPU time per frame (mean over frames, output files off:
  XDMF, summary and checkpoint are not written; the shell set-up is reported apart), peak
  resident memory of the process during the configuration (VmHWM reset before each run),
  shell and body Newton iterations, the 1-minute load average before and after.

Knobs (:data:`GROUP_ORDER`, most important first): subdivision levels, Hessian mode (exact,
gauss_newton, mixed = projected far from the minimum then exact), PSD Hessian + loose
tolerance combinations, the shifted-Hessian schedule (the solver's ten-fold factors), shell
Newton tolerance, body mesh size, body P1/P2, time step
(statics: load frames; dynamics: steps per frame at a fixed frame interval), cluster count
and sigma, one- vs two-way coupling (monolithic, and the fixed point for comparison), the
assembled-penalty linear solver and modified Newton (factorisation reuse), and on
request (``--only newton_cap``) the iteration cap. Knobs measured as dominated or
redundant on the h = 5 cm sweep are left out, each with its reason (:data:`DROPPED`, also
in the JSON's ``notes``).

Writes ``benchmarks/results/speed_accuracy.json`` (``--out``; rewritten atomically after
every configuration, so a killed run loses at most the configuration it was running;
``--resume`` reruns only what is missing, ``--budget`` stops starting configurations after
a number of minutes), the Pareto plot ``speed_accuracy.png`` (process CPU time of all frames
vs rms_rel, and in a second panel vs the bending energy error (:data:`BENDING`), log-log:
every setting reaches the same final load, so settings with other frame counts compare
fairly; CPU time because the machine is shared) and the Markdown table
of the Pareto-optimal settings ``speed_accuracy_pareto.md`` (both fronts; converged
settings only; a slower setting must lower the error by more than 1 % to be on the front).

Usage::

    python benchmarks/speed_accuracy.py --quick              # tiny sizes, ~30 s
    python benchmarks/speed_accuracy.py --list               # the configurations, in order
    python benchmarks/speed_accuracy.py --resume --budget 50 # default scene, full size
    python benchmarks/speed_accuracy.py --only subdivision hessian --resume
    python benchmarks/speed_accuracy.py --scene scenes/ball_sofa_coarse.toml \\
        --set time.frames=6 --levels 0 1 --ref-set time.steps_per_frame=4 \\
        --ref-set body.dt=0.0025 --mesh-h 0.15 0.3 \\
        --only subdivision hessian combo newton_rtol mesh body time \\
        --out benchmarks/results/speed_accuracy_ball_sofa.json --resume --budget 25
    python benchmarks/speed_accuracy.py --from-json --note "..."   # table, plot, a remark

With ``--ref-set`` the group "body" also runs the reference's body and time step with the
scene's (and coarser) shells, which separates the body's share of the error from the
shell's.

Runs are serial (one rank); timings on a shared machine are contended.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.shell_solve import proc_status_mib, reset_peak_rss
from meshes.errors import InputError, SolverError
from models.backend import MPI
from validation.measure import normal_heights, shell_wavelength
from wrinkles.output import write_text_atomic
from wrinkles.presets import PRESET_ROWS
from wrinkles.runner import prepare, run_frames
from wrinkles.scene import load_scene

RESULTS = Path(__file__).resolve().parent / "results"
QUIET = ["output.render=false", "output.xdmf=false"]
"""Overrides of every run: no XDMF files, no rendering (timing the solve, not the disk; the
summary and the checkpoint are always written)."""

QUICK_BASE = ["mesh.params.h=0.05", "time.frames=2", "body.dt=0.5",
              "shell.solver.max_iterations=200"]
"""``--quick``: coarse body mesh, 2 frames of the same total load (tiny, seconds)."""

REFERENCE = ["body.degree=2", "shell.solver.options.energy.hessian_mode=\"exact\"",
             "shell.solver.options.newton.far_hessian=\"\"", "shell.solver.rtol=1e-8",
             "shell.solver.max_iterations=500", "shell.solver.method=\"direct\""]
"""The reference's settings besides its subdivision level (exact Newton: direct solves)."""

DIRECT = 'shell.solver.method="direct"'
"""The direct linear solve, for the rows that measure a direct-solver option."""


BENDING = "bending_energy_rel_error"
"""The second Pareto axis: wrinkle patterns are branches of a bifurcation, so two settings
can find wrinkles of the same energy and wavelength at shifted phases (a large position
distance); the bending energy error measures the pattern without its phase."""

PARETO_MARGIN = 0.01
"""Relative error decrease below which a slower setting is not counted as more accurate."""


@dataclasses.dataclass(frozen=True)
class Config:
    """One point of the sweep.

    Attributes:
        name: unique label.
        group: the knob swept ("subdivision", "hessian", ...; "combo" for combinations).
        overrides: ``key=value`` scene overrides on top of the base.

    """

    name: str
    group: str
    overrides: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class SceneFacts:
    """The scene's own settings the sweep varies (read with the base overrides applied).

    Attributes:
        levels: shell subdivision levels.
        hessian: shell Hessian mode (``shell.solver.options.energy.hessian_mode``).
        far_hessian: PSD mode used far from the minimum ("" for none).
        rtol: shell Newton relative tolerance.
        h: body mesh size of the builder [m]; ``None`` for a mesh file.
        dynamic: whether the body is time dependent (the time knob is then the number of
            steps per frame at a fixed frame interval, else the number of load frames).
        dt: body time step [s] (statics: load parameter per frame).
        steps_per_frame: body steps per frame.
        frames: number of frames.

    """

    levels: int
    hessian: str
    far_hessian: str
    rtol: float
    h: float | None
    dynamic: bool
    dt: float
    steps_per_frame: int
    frames: int


def scene_facts(scene_path: Path, base: list[str]) -> SceneFacts:
    """Read the :class:`SceneFacts` of ``scene_path`` with the overrides ``base``."""
    scene = load_scene(scene_path, [*base, *QUIET])
    if scene.shell is None:
        raise InputError(f"{scene_path}: the speed/accuracy sweep needs a [shell] table")
    h = scene.mesh.params.get("h") if scene.mesh.builder else None
    return SceneFacts(levels=scene.shell.subdivision.levels,
                      hessian=scene.shell.internals.energy.hessian_mode,
                      far_hessian=scene.shell.internals.newton.far_hessian,
                      rtol=scene.shell.solver.rtol,
                      h=None if h is None else float(h),
                      dynamic=scene.body.dynamics != "static", dt=scene.body.dt,
                      steps_per_frame=scene.time.steps_per_frame,
                      frames=scene.time.frames)


HESSIAN_MODE = "shell.solver.options.energy.hessian_mode"
FAR_HESSIAN = "shell.solver.options.newton.far_hessian"
HESSIANS: dict[str, tuple[str, ...]] = {
    "exact": (f'{HESSIAN_MODE}="exact"', f'{FAR_HESSIAN}=""'),
    "gauss_newton": (f'{HESSIAN_MODE}="gauss_newton"', f'{FAR_HESSIAN}=""'),
    "mixed": (f'{HESSIAN_MODE}="exact"', f'{FAR_HESSIAN}="projected"'),
    "projected": (f'{HESSIAN_MODE}="projected"', f'{FAR_HESSIAN}=""'),
}
"""Hessian modes of the sweep: mixed = projected far from the minimum, then exact."""

MODIFIED = "shell.solver.options.newton.modified.enabled=true"
"""Modified Newton: one factorisation reused over up to 4 Newton iterations (and frames) while
the gradient norm falls by half per iteration (:class:`solvers.shell_newton.ModifiedNewtonOptions`).
One-way ``modified`` measured 2.24 against 2.51 s (``base``), on the position front (rms_rel
0.131 against 0.148) but with larger bending-energy and wavelength errors (17.9 / 6.3 %
against 16.2 / 3.7 %): another wrinkled minimum. The monolithic two-way solve does not reuse
factorisations (its row would equal ``two_way``)."""

GROUP_ORDER: tuple[str, ...] = ("base", "subdivision", "hessian", "combo", "shift", "newton_rtol",
                                "mesh", "body", "time", "clusters", "sigma", "coupling",
                                "linear", "newton_cap")
"""Knob groups in the order they run (most important first: a run cut short by the
machine's budget keeps the knobs that decide the presets)."""

DROPPED: dict[str, str] = {
    "levels=<scene's own>, hessian=<scene's own>": "duplicates of the row 'base'",
    "hessian=projected": "dominated: the same minimiser as 'mixed' (projected far from the "
                         "minimum, then exact) at 2.2x its time on the h = 5 cm sweep (5.66 "
                         "against 2.59 s/frame), and the per-stencil eigen clamp costs 23-27 "
                         "us per vertex (benchmarks/shell_kernels.py) on every iteration",
    "rtol=1e-5, rtol=1e-7": "redundant: on the h = 5 cm sweep every rtol from 1e-3 to 1e-7 "
                            "gave the same final shell (rms_rel 0.245 to 3 digits); 1e-3, "
                            "1e-4 (cheaper) and the reference's 1e-8 bracket them",
    "max_it=10, max_it=30 (newton_cap)": "an iteration cap stops the solve unconverged, and "
                                         "unconverged rows are never on the Pareto front; "
                                         "run with --only newton_cap",
    "linear=superlu_dist": "dominated: 6.4x the time of MUMPS on the h = 5 cm sweep (8.3 "
                           "against 1.3 s/frame) for the same system",
    "sigma=0.0067": "redundant: the physical sizing of the default scene already gives "
                    "sigma = lambda/pi = 6.7 mm at spacing lambda/2 = 10.5 mm",
    "combinations at fewer levels than the scene's": "redundant: at 0 or 1 levels every "
                                                     "Hessian / rtol combination of the h = 5 "
                                                     "cm sweep gave the error of its level "
                                                     "row to 3 digits",
}
"""Knobs of the issue's list left out of the default sweep, and why (into the JSON)."""


def subdivision_knobs(levels: list[int], facts: SceneFacts) -> list[Config]:
    """Subdivision levels other than the scene's own."""
    return [Config(f"levels={n}", "subdivision", (f"shell.subdivision.levels={n}",))
            for n in levels if n != facts.levels]


def hessian_knobs(facts: SceneFacts) -> list[Config]:
    """Hessian modes other than the scene's own (projected: dropped, see :data:`DROPPED`)."""
    own = "mixed" if facts.far_hessian == "projected" else facts.hessian
    return [Config(f"hessian={m}", "hessian", HESSIANS[m])
            for m in ("exact", "gauss_newton", "mixed") if m != own]


def shift_knobs() -> list[Config]:
    """The ten-fold shift schedule (growth 10, decay 10) against the static scenes' 5 / 2
    (:class:`solvers.linear.ShiftOptions`, ``benchmarks/shift_schedule.py``): the same
    tolerance, but a path of other step lengths may settle in another wrinkle branch."""
    return [Config("shift=10/10", "shift", ("shell.solver.options.newton.shift.growth=10.0",
                                            "shell.solver.options.newton.shift_decay=10.0",
                                            "shell.solver.options.newton.shift.max_shifts=14"))]


def newton_knobs(facts: SceneFacts) -> list[Config]:
    """Shell Newton tolerance (and, run only on request, the iteration cap)."""
    c = [Config(f"rtol={r:g}", "newton_rtol", (f"shell.solver.rtol={r!r}",))
         for r in (1e-3, 1e-4, 1e-8) if r != facts.rtol]
    return c + [Config(f"max_it={k}", "newton_cap", (f"shell.solver.max_iterations={k}",))
                for k in (10, 30)]


def mesh_knobs(facts: SceneFacts, mesh_h: list[float] | None) -> list[Config]:
    """Body mesh sizes (default: 1.5x and 2x the scene's, i.e. cheaper bodies and shells)."""
    if facts.h is None:
        return []
    sizes = mesh_h or [round(1.5 * facts.h, 6), round(2.0 * facts.h, 6)]
    return [Config(f"h={h:g}", "mesh", (f"mesh.params.h={h!r}",)) for h in sizes]


def time_knobs(facts: SceneFacts) -> list[Config]:
    """Time step: halved and doubled at a fixed frame interval (dynamics), else the number
    of load frames halved and doubled at the same final load (statics)."""
    if facts.dynamic:
        spf = facts.steps_per_frame
        return [Config(f"steps_per_frame={k}", "time",
                       (f"time.steps_per_frame={k}", f"body.dt={facts.dt * spf / k!r}"))
                for k in (spf // 2, 2 * spf) if k >= 1 and k != spf]
    total = facts.dt * facts.frames
    return [Config(f"frames={n}", "time", (f"time.frames={n}", f"body.dt={total / n!r}"))
            for n in (facts.frames // 2, 2 * facts.frames) if n >= 1 and n != facts.frames]


def other_knobs() -> list[Config]:
    """Clusters, sigma, body degree, coupling and linear solver."""
    c = [Config(f"clusters={k}", "clusters", (f"shell.clusters.count={k}",)) for k in (100, 400)]
    c += [Config(f"sigma={s:g}", "sigma", ("shell.clusters.spacing=0.0105",
                                           f"shell.clusters.sigma={s!r}"))
          for s in (0.0035, 0.013)]
    c += [Config("body=P2", "body", ("body.degree=2",))]
    two_way = ('shell.coupling.mode="two_way"',)
    c += [Config("two_way", "coupling", two_way),
          Config("two_way+fixed_point", "coupling",
                 (*two_way, 'shell.solver.options.coupling.scheme="implicit"',
                  "shell.solver.options.coupling.max_iterations=80", DIRECT))]
    return c + [Config("method=direct", "linear", (DIRECT,)),
                Config("linear=assembled_mumps", "linear",
                       ('shell.solver.options.energy.penalty_hessian="assembled"',
                        'shell.solver.options.newton.linear.backend="mumps"', DIRECT)),
                Config("modified", "linear", (MODIFIED, DIRECT))]


def combinations(facts: SceneFacts, levels: list[int] | None = None) -> list[Config]:
    """PSD Hessians with a loose tolerance at the scene's level (preset candidates), and the
    cheapest of them (Gauss-Newton, rtol 1e-3) at the finer levels of ``levels``."""
    def combo(n: int, mode: str) -> Config:
        return Config(f"L{n}+{mode}+rtol=0.001", "combo",
                      (f"shell.subdivision.levels={n}", *HESSIANS[mode],
                       "shell.solver.rtol=0.001"))

    finer = [n for n in levels or [] if n > facts.levels]
    return ([combo(facts.levels, m) for m in ("gauss_newton", "mixed", "projected")]
            + [combo(n, "gauss_newton") for n in finer])


def reference_body(ref_extra: list[str], levels: list[int], facts: SceneFacts
                   ) -> list[Config]:
    """The reference's body and time step (P2 and the ``--ref-set`` overrides) with the
    scene's shell, and with the coarser shells of ``levels``: separates the body's share of
    the error from the shell's (only with ``--ref-set``; else it is the row body=P2)."""
    if not ref_extra:
        return []
    body = ("body.degree=2", *ref_extra)
    return [Config("body=reference", "body", body)] + [
        Config(f"L{n}+body=reference", "body", (f"shell.subdivision.levels={n}", *body))
        for n in levels if n < facts.levels]


def sweep(levels: list[int], facts: SceneFacts, only: list[str] | None,
          mesh_h: list[float] | None = None, ref_extra: list[str] | None = None
          ) -> list[Config]:
    """All configurations in :data:`GROUP_ORDER`; ``only``: these groups (and "base").

    Without ``only`` the group "newton_cap" is left out (see :data:`DROPPED`).
    """
    configs = [Config("base", "base"), *subdivision_knobs(levels, facts),
               *hessian_knobs(facts), *shift_knobs(), *newton_knobs(facts),
               *mesh_knobs(facts, mesh_h),
               *time_knobs(facts), *other_knobs(), *reference_body(ref_extra or [], levels, facts),
               *combinations(facts, levels)]
    wanted = set(only) if only else set(GROUP_ORDER) - {"newton_cap"}
    chosen = [c for c in configs if c.group in wanted or c.group == "base"]
    return sorted(chosen, key=lambda c: GROUP_ORDER.index(c.group))


# --------------------------------------------------------------------------------------------
# Running one configuration


def frame_done(marks: list[float], line: str) -> None:
    """Progress callback of a frame: note the process CPU time, echo the line to stderr."""
    marks.append(time.process_time())
    print(f"    {line}  cpu={time.process_time():.1f} s", file=sys.stderr, flush=True)


def run_config(scene_path: Path, overrides: list[str]) -> dict[str, Any]:
    """Run the scene with ``overrides`` (serial, output off); time it and keep the final shell.

    Per frame, the wall time (the runner's record) and the process CPU time (user + system
    of this process, :func:`time.process_time`, read at each frame's progress line): on a
    shared machine the wall time includes waiting for a core, the CPU time does not.

    Returns:
        times, peak memory, iterations, the 1-minute load average before and after, and the
        final shell arrays (``rest``, ``x``, ``target``, ``faces``) plus the bending energy
        and vertex count.

    """
    scene = load_scene(scene_path, [*overrides, *QUIET])
    if scene.shell is None:
        raise InputError(f"{scene_path}: the speed/accuracy sweep needs a [shell] table")
    reset_peak_rss()
    rss0, load0 = proc_status_mib("VmRSS"), os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="speed_accuracy_") as tmp:
        t0, c0 = time.perf_counter(), time.process_time()
        run = prepare(scene, Path(tmp), MPI.COMM_WORLD)
        marks = [time.process_time()]
        setup, setup_cpu = time.perf_counter() - t0, marks[0] - c0
        run_frames(run, log=lambda line: frame_done(marks, line))
    shell = run.shell
    assert shell is not None
    walls, cpus = [r.wall_time for r in run.records], np.diff(marks[:len(run.records) + 1])
    terms = shell.energy.evaluate(shell.x, order=0).terms
    return {"setup_time": setup, "setup_cpu_time": setup_cpu, "frame_times": walls,
            "frame_cpu_times": [float(c) for c in cpus],
            "time_per_frame": float(np.mean(walls)), "cpu_per_frame": float(np.mean(cpus)),
            "peak_rss_mib": proc_status_mib("VmHWM"),
            "peak_rss_delta_mib": proc_status_mib("VmHWM") - rss0,
            "load_avg_1min": [load0, os.getloadavg()[0]],
            "body_iterations": [r.newton_iterations for r in run.records],
            "shell_iterations": [r.details.get("shell_iterations") for r in run.records],
            "shell_converged": [r.details.get("shell_converged") for r in run.records],
            "shell_factorizations": [r.details.get("shell_factorizations")
                                     for r in run.records],
            "shell_shifted_iterations": [r.details.get("shell_shifted_iterations")
                                         for r in run.records],
            "shell_seconds": [r.details.get("shell_time_total") for r in run.records],
            "shell_final_energy": run.records[-1].details.get("shell_energy")
            if run.records else None,
            "coupling_iterations": [r.details.get("coupling_iterations") for r in run.records],
            "vertices": int(shell.rest.shape[0]), "bending_energy": float(terms.get("bending",
                                                                                    0.0)),
            "arrays": {"rest": shell.rest.copy(), "x": shell.x.copy(), "target": shell.y.copy(),
                       "faces": shell.topology.faces.copy()}}


# --------------------------------------------------------------------------------------------
# Comparison with the reference


def barycentric_interpolate(rest: np.ndarray, faces: np.ndarray, values: np.ndarray,
                            points: np.ndarray, candidates: int = 8) -> np.ndarray:
    """Interpolate nodal ``values`` of a triangle mesh at ``points`` (closest triangle).

    For each point the ``candidates`` triangles with the nearest centroids are tried; the
    point is projected onto each triangle's plane, its barycentric coordinates clipped to the
    triangle and renormalised, and the triangle at the smallest distance is used.
    """
    tri = rest[faces]
    _, idx = cKDTree(tri.mean(axis=1)).query(points, k=min(candidates, len(faces)))
    idx = idx.reshape(len(points), -1)
    best = np.full(len(points), np.inf)
    out = np.zeros((len(points),) + values.shape[1:])
    for j in range(idx.shape[1]):
        f = idx[:, j]
        lam = _barycentric(tri[f], points)
        p = np.einsum("nk,nkd->nd", lam, tri[f])
        dist = np.linalg.norm(p - points, axis=1)
        better = dist < best
        best[better] = dist[better]
        out[better] = np.einsum("nk,nk...->n...", lam[better], values[faces[f[better]]])
    return out


def _barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Clipped, renormalised barycentric coordinates of ``p`` projected onto triangles."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (np.einsum("ij,ij->i", u, v) for u, v in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    lam = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    return lam / np.maximum(lam.sum(axis=1, keepdims=True), 1e-300)


def compared_positions(ref: dict[str, np.ndarray], cand: dict[str, np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, str]:
    """Reference and candidate final positions on common points, and how they were matched."""
    n = min(len(ref["rest"]), len(cand["rest"]))
    if np.allclose(ref["rest"][:n], cand["rest"][:n], rtol=0.0, atol=1e-12):
        return ref["x"][:n], cand["x"][:n], "common_vertices"
    disp = cand["x"] - cand["rest"]
    at_ref = barycentric_interpolate(cand["rest"], cand["faces"], disp, ref["rest"])
    return ref["x"], ref["rest"] + at_ref, "interpolated"


def wrinkle_wavelength(arrays: dict[str, np.ndarray]) -> float | None:
    """Dominant wrinkle wavelength [m] of the final shell (:mod:`validation.measure`).

    The normal deviation from the target, ``(x - y) . n_y``, on the flat lateral faces
    parallel to the longest axis of the rest shell (the compression axis of the bar), one
    mean edge length inside the faces' borders (2 leave no vertex on the 5 cm faces of a
    2-level shell on h = 5 cm tets), lines one edge length wide.
    ``None`` when the shell has no such faces (e.g. a curved body).
    """
    rest, faces = arrays["rest"], arrays["faces"]
    edge = float(np.mean(np.linalg.norm(rest[faces[:, 1]] - rest[faces[:, 0]], axis=1)))
    axis = int(np.argmax(np.ptp(rest, axis=0)))
    heights = normal_heights(arrays["x"], arrays["target"], faces)
    try:
        return shell_wavelength(rest, faces, heights, axis, edge, edge).wavelength
    except InputError:
        return None


def errors(ref: dict[str, Any], cand: dict[str, Any]) -> dict[str, Any]:
    """Error metrics of a run against the reference (final frame)."""
    xr, xc, how = compared_positions(ref["arrays"], cand["arrays"])
    d = np.linalg.norm(xc - xr, axis=1)
    scale = float(np.sqrt(np.mean(np.sum((ref["arrays"]["x"] - ref["arrays"]["rest"]) ** 2,
                                         axis=1))))
    lam_ref, lam = ref.get("wavelength"), wrinkle_wavelength(cand["arrays"])
    eb_ref = ref["bending_energy"]
    return {"matched": how, "points": int(len(d)), "rms": float(np.sqrt(np.mean(d * d))),
            "max": float(d.max()), "rms_rel": float(np.sqrt(np.mean(d * d))) / max(scale, 1e-300),
            "wavelength": lam,
            "wavelength_rel_error": (abs(lam - lam_ref) / lam_ref if lam and lam_ref else None),
            "bending_energy_rel_error": (abs(cand["bending_energy"] - eb_ref) / eb_ref
                                         if eb_ref > 0 else None)}


# --------------------------------------------------------------------------------------------
# The reference (stored, regenerated when missing)


def reference_path(results: Path, scene: Path, quick: bool) -> Path:
    """File of the stored reference run."""
    return results / f"speed_accuracy_reference_{scene.stem}{'_quick' if quick else ''}.npz"


def reference_key(scene: Path, overrides: list[str]) -> str:
    """The settings a stored reference (and a resumed row) must match."""
    return json.dumps({"scene": str(scene.resolve()), "overrides": overrides, "version": 5})


def load_or_make_reference(path: Path, scene: Path, overrides: list[str],
                           log: Callable[[str], None]) -> dict[str, Any]:
    """Read the stored reference if its settings match, else run and store it."""
    key = reference_key(scene, overrides)
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) == key:
                log(f"reference: {path.name} (stored)")
                meta = json.loads(str(data["meta"]))
                return {**meta, "arrays": {k: data[k] for k in ("rest", "x", "target",
                                                                "faces")}}
    log(f"reference: running {' '.join(overrides)} ...")
    ref = run_config(scene, overrides)
    ref["wavelength"] = wrinkle_wavelength(ref["arrays"])
    meta = {k: v for k, v in ref.items() if k != "arrays"}
    np.savez(path, key=np.array(key), meta=np.array(json.dumps(meta)), **ref["arrays"])
    log(f"reference: {ref['vertices']} vertices, {ref['time_per_frame']:.2f} s/frame wall, "
        f"{ref['cpu_per_frame']:.2f} s/frame CPU, stored in {path.name}")
    return ref


# --------------------------------------------------------------------------------------------
# Pareto front, table, plot


def converged(row: dict[str, Any]) -> bool:
    """Whether every frame's shell solve of a row converged (rows without the record: yes)."""
    return all(c is not False for c in row.get("shell_converged", []))


def run_time(row: dict[str, Any]) -> float:
    """Process CPU time [s] of all frames of a row (wall time for rows without it).

    Every row reaches the same final load (or time), so this, not the time per frame,
    compares settings with different frame counts fairly; the CPU time, not the wall time,
    because the machine is shared (the wall time includes waiting for a core).
    """
    return float(sum(row.get("frame_cpu_times") or row["frame_times"]))


def pareto(rows: list[dict[str, Any]], metric: str = "rms_rel") -> list[dict[str, Any]]:
    """Converged rows not dominated in (CPU run time, ``metric``): no other row is at least
    as fast and at least as accurate and strictly better in one; sorted by time.

    ``metric`` is an error of the row: "rms_rel" (shell positions) or
    "bending_energy_rel_error". Rows whose shell solve stopped unconverged (an iteration cap)
    are left out: their distance to the reference is not an accuracy the setting can
    promise. A slower row must lower the error by more than ``PARETO_MARGIN`` (relative) to
    count as more accurate.
    """
    ok = sorted((r for r in rows if r.get(metric) is not None and converged(r)),
                key=lambda r: (run_time(r), r[metric]))
    front: list[dict[str, Any]] = []
    for r in ok:
        if not front or r[metric] < (1.0 - PARETO_MARGIN) * front[-1][metric]:
            front.append(r)
    return front


def _fmt(value: Any, spec: str = ".3g") -> str:
    """Format a number (or '-' for None)."""
    return "-" if value is None else format(value, spec)


def markdown_table(front: list[dict[str, Any]]) -> str:
    """Markdown table of the Pareto-optimal settings."""
    lines = ["| setting | overrides | vertices | frames | wall s/frame | CPU s/frame | "
             "CPU s (all frames) | peak MiB | rms_rel | max [m] | E_B rel | lambda [m] | "
             "shell its |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in front:  # shell its: shell Newton iterations summed over the frames
        lines.append(f"| {r['name']} | `{' '.join(r['overrides']) or '(scene)'}` | "
                     f"{r['vertices']} | {len(r['frame_times'])} | {r['time_per_frame']:.3g} | "
                     f"{_fmt(r.get('cpu_per_frame'))} | "
                     f"{run_time(r):.3g} | {r['peak_rss_mib']:.0f} | "
                     f"{_fmt(r['rms_rel'])} | {_fmt(r['max'])} | "
                     f"{_fmt(r['bending_energy_rel_error'])} | {_fmt(r['wavelength'])} | "
                     f"{sum(i or 0 for i in r['shell_iterations'])} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict[str, Any]], fronts: dict[str, list[dict[str, Any]]],
         path: Path) -> None:
    """Pareto plots, one panel per error metric: CPU run time vs error (log-log), one colour
    per knob, crosses for unconverged rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(fronts), figsize=(7 * len(fronts), 5), squeeze=False)
    groups = sorted({r["group"] for r in rows})
    colors = dict(zip(groups, plt.get_cmap("tab20")(np.linspace(0.0, 1.0, max(len(groups), 1))),
                      strict=False))
    for ax, (metric, front) in zip(axes[0], fronts.items(), strict=True):
        for r in (r for r in rows if r.get(metric)):
            ax.scatter(run_time(r), r[metric], color=colors[r["group"]],
                       marker="o" if converged(r) else "x")
        ax.plot([run_time(r) for r in front], [r[metric] for r in front], "k--", lw=1)
        for r in front:
            ax.annotate(r["name"], (run_time(r), r[metric]), fontsize=7)
        ax.set(xscale="log", yscale="log", title=f"Pareto front on {metric}",
               xlabel="CPU time of all frames (same final load) [s]",
               ylabel={"rms_rel": "shell position RMS error / reference RMS displacement"}.get(
                   metric, "|E_B - E_B,ref| / E_B,ref"))
    handles = [plt.Line2D([], [], color=colors[g], marker="o", ls="", label=g) for g in groups]
    axes[0][0].legend(handles=handles, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# Main


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line flags."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", type=Path, default=Path("scenes/default.toml"))
    p.add_argument("--quick", action="store_true", help="tiny sizes (seconds), few knobs")
    p.add_argument("--levels", type=int, nargs="+", default=None,
                   help="subdivision levels swept (default 0 1 2 3; --quick 0 1); the "
                   "scene's own level is the row 'base'")
    p.add_argument("--ref-levels", type=int, default=None,
                   help="subdivision levels of the reference (default 3; --quick 2)")
    p.add_argument("--ref-set", dest="ref_overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="extra override of the reference only (e.g. a "
                   "smaller time step: time.steps_per_frame=4 body.dt=0.0025)")
    p.add_argument("--only", nargs="+", default=None, choices=GROUP_ORDER,
                   help="only these knob groups (default: all but newton_cap)")
    p.add_argument("--mesh-h", type=float, nargs="+", default=None,
                   help="body mesh sizes of the 'mesh' group (default 1.5x and 2x the scene's)")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="scene override applied to every run")
    p.add_argument("--out", type=Path, default=RESULTS / "speed_accuracy.json")
    p.add_argument("--resume", action="store_true",
                   help="keep the rows of --out run with the same settings (scene, base and "
                   "reference overrides, row overrides) and run only the others")
    p.add_argument("--budget", type=float, default=None, metavar="MINUTES",
                   help="start no new configuration after this many minutes of wall time "
                   "(the rest is listed as not run; --resume continues later)")
    p.add_argument("--note", default=None,
                   help="a remark on the scene stored in the JSON's notes (also with "
                   "--from-json; make paper prints it)")
    p.add_argument("--list", action="store_true",
                   help="print the configurations (in run order) and exit")
    p.add_argument("--from-json", action="store_true",
                   help="only redo the Pareto front, table and plot of the JSON in --out")
    return p.parse_args(argv)


def write_json(doc: dict[str, Any], out: Path) -> None:
    """Write ``doc`` to ``out`` atomically (a killed run leaves the previous complete file)."""
    write_text_atomic(out, json.dumps(doc, indent=2) + "\n")


def preset_map(doc: dict[str, Any]) -> dict[str, str]:
    """Quality -> measured row name (:data:`wrinkles.presets.PRESET_ROWS`), only for the
    full-size default scene the presets are chosen on (else empty)."""
    full = not doc["quick"] and not doc["base_overrides"]
    return dict(PRESET_ROWS) if full and Path(doc["scene"]).stem == "default" else {}


def summarize(doc: dict[str, Any], out: Path) -> str:
    """Pareto front of ``doc``'s rows into ``doc``, JSON, Markdown table and plot; the table."""
    front = pareto([r for r in doc["rows"] if "error" not in r])
    by_energy = pareto([r for r in doc["rows"] if "error" not in r], BENDING)
    doc["pareto"] = [r["name"] for r in front]
    doc["pareto_bending"] = [r["name"] for r in by_energy]
    doc["presets"] = preset_map(doc)
    write_json(doc, out)
    table = markdown_table(front)
    out.with_name(out.stem + "_pareto.md").write_text(
        f"{table}\nFront on the bending energy error ({BENDING}):\n\n"
        f"{markdown_table(by_energy)}")
    plot([r for r in doc["rows"] if "error" not in r], {"rms_rel": front, BENDING: by_energy},
         out.with_suffix(".png"))
    return table


def run_row(scene: Path, base: list[str], config: Config, ref: dict[str, Any]
            ) -> dict[str, Any]:
    """Run one configuration and compare it; a failed solve becomes a row with its error."""
    row: dict[str, Any] = {"name": config.name, "group": config.group,
                           "overrides": list(config.overrides)}
    try:
        result = run_config(scene, [*base, *config.overrides])
    except (SolverError, InputError) as exc:
        return {**row, "error": f"{type(exc).__name__}: {exc}"}
    except Exception as exc:  # noqa: BLE001  (a crash of one setting is a result too)
        return {**row, "error": "".join(traceback.format_exception_only(exc)).strip()}
    arrays_free = {k: v for k, v in result.items() if k != "arrays"}
    return {**row, **arrays_free, **errors(ref, result)}


HEADER = (f"{'setting':28s} {'verts':>7s} {'wall/fr':>8s} {'CPU/fr':>8s} {'peakMiB':>8s} "
          f"{'rms_rel':>9s} {'max[m]':>9s} {'E_B rel':>9s} {'lambda':>8s} {'its':>5s}")
"""Header of the printed table (:func:`print_row`)."""


def print_row(r: dict[str, Any]) -> None:
    """One line of the table."""
    if "error" in r:
        print(f"{r['name']:28s} FAILED {r['error'][:90]}", flush=True)
        return
    print(f"{r['name'] + ('' if converged(r) else ' (unconv.)'):28s} {r['vertices']:7d} "
          f"{r['time_per_frame']:8.3f} {_fmt(r.get('cpu_per_frame'), '8.3f')} "
          f"{r['peak_rss_mib']:8.0f} {r['rms_rel']:9.3e} {r['max']:9.3e} "
          f"{_fmt(r['bending_energy_rel_error'], '9.3e')} {_fmt(r['wavelength'], '8.4f')} "
          f"{sum(i or 0 for i in r['shell_iterations']):5d}", flush=True)


def row_key(doc: dict[str, Any], config: Config) -> str:
    """What a stored row must match to be reused by ``--resume``."""
    return json.dumps({"reference": doc["reference"]["key"], "base": doc["base_overrides"],
                       "overrides": list(config.overrides)})


def stored_rows(out: Path, resume: bool) -> dict[str, dict[str, Any]]:
    """Rows of an earlier run in ``out`` by their ``key`` (empty without ``--resume``)."""
    if not resume or not out.is_file():
        return {}
    return {r["key"]: r for r in json.loads(out.read_text()).get("rows", []) if "key" in r}


def new_document(args: argparse.Namespace, base: list[str], ref: dict[str, Any],
                 ref_overrides: list[str], ref_levels: int) -> dict[str, Any]:
    """The JSON document before its rows: scene, settings, reference, machine, notes."""
    return {"scene": str(args.scene), "quick": args.quick, "base_overrides": base,
            "reference": {k: v for k, v in ref.items() if k != "arrays"} | {
                "levels": ref_levels, "overrides": ref_overrides,
                "key": reference_key(args.scene, ref_overrides)},
            "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                        "note": "serial runs on a shared machine: wall times are contended; "
                                "the CPU time of the process is the fairer figure and the "
                                "Pareto axis; load_avg_1min per row"},
            "notes": {"dropped": DROPPED, "group_order": list(GROUP_ORDER), "not_run": [],
                      "scene": args.note or ""},
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "rows": []}


def run_sweep(args: argparse.Namespace, doc: dict[str, Any], configs: list[Config],
              ref: dict[str, Any]) -> None:
    """Run (or reuse) every configuration into ``doc["rows"]``, writing the JSON after each.

    With ``--resume`` a configuration whose row is stored in ``--out`` with the same key
    (:func:`row_key`) is not run again, and stored rows of groups not selected now are kept,
    so runs of a few groups at a time accumulate in one JSON.
    """
    stored, started = stored_rows(args.out, args.resume), time.perf_counter()
    print(HEADER)
    for config in configs:
        key = row_key(doc, config)
        if key in stored:
            doc["rows"].append(stored[key])
        elif args.budget is not None and time.perf_counter() - started > 60.0 * args.budget:
            doc["notes"]["not_run"].append(config.name)
            continue
        else:
            doc["rows"].append({**run_row(args.scene, doc["base_overrides"], config, ref),
                                "key": key})
            write_json(doc, args.out)
        print_row(doc["rows"][-1])
    done = {r.get("key") for r in doc["rows"]}
    doc["rows"] += [r for k, r in stored.items() if k not in done]  # other groups, kept


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Reference, sweep, table, JSON, plot; return the JSON document."""
    args = parse_args(argv)
    if args.from_json:
        doc = json.loads(args.out.read_text())
        if args.note is not None:
            doc.setdefault("notes", {})["scene"] = args.note
        print("Pareto-optimal settings:\n" + summarize(doc, args.out))
        return doc
    levels = args.levels or ([0, 1] if args.quick else [0, 1, 2, 3])
    ref_levels = args.ref_levels if args.ref_levels is not None else (2 if args.quick else 3)
    base = [*(QUICK_BASE if args.quick else []), *args.overrides]
    ref_overrides = [*base, *REFERENCE, f"shell.subdivision.levels={ref_levels}",
                     *args.ref_overrides]
    configs = sweep(levels, scene_facts(args.scene, base), args.only, args.mesh_h,
                    args.ref_overrides)
    if args.list:
        print("\n".join(f"{c.group:12s} {c.name:28s} {' '.join(c.overrides)}" for c in configs))
        return {"configs": [dataclasses.asdict(c) for c in configs]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    run_config(args.scene, [*base, "shell.subdivision.levels=0", "time.frames=1"])  # JIT warm-up
    ref = load_or_make_reference(reference_path(args.out.parent, args.scene, args.quick),
                                 args.scene, ref_overrides, print)
    doc = new_document(args, base, ref, ref_overrides, ref_levels)
    run_sweep(args, doc, configs, ref)
    print("\nPareto-optimal settings:\n" + summarize(doc, args.out))
    if doc["notes"]["not_run"]:
        print(f"not run (budget): {' '.join(doc['notes']['not_run'])}; rerun with --resume")
    return doc


if __name__ == "__main__":
    main()
