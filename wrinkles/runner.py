"""The frame loop of ``wrinkles run``: mesh, body, then per frame a list of stages and output.

Algorithm 1 of the draft (Rémillard & Kry 2013 embedded thin shells) advances the coarse body
and then the embedded shell once per frame. Here one frame runs the *stages* in order, each a
callable ``stage(frame) -> dict`` that advances its part of the model and returns the numbers
it wants in the frame record::

    run = prepare(scene, out, comm)          # mesh, body, body stage, shell stage, output files
    run_frames(run, log)

A scene with a ``[shell]`` table gets the embedded-shell stage of :mod:`wrinkles.shell_stage`
after the body stage (``shell.xdmf`` beside ``body.xdmf``); with ``shell.coupling.mode =
"two_way"`` one coupled stage (:mod:`wrinkles.two_way`) replaces body and shell stages.
``output.render`` renders the shell (:mod:`wrinkles.render`) when the run completes.

A scene with ``[[rigid.balls]]`` (:mod:`models.rigid`) gets each ball's sphere as a contact of
the body (after ``[[body.contacts]]``), and the body stage becomes the ``body+rigid`` stage:
every body step is a coupled step of balls and body (interface iteration ball position <->
body solve, :class:`solvers.coupling.BallCoupling`). Its record adds, per frame, each ball's
centre, velocity, contact force and penetration (max over the frame's steps, fraction of the
radius), the interface iterations per step and the cumulative momentum balance; the balls'
state is the checkpoint's ``rigid`` arrays. The shell stages (one- and two-way) call this
stage in place of the plain body stage.

After every frame the summary and a checkpoint of the body state (:mod:`wrinkles.checkpoint`,
with the shell's state as its ``shell`` arrays) are written; ``prepare(..., restart=True)``
continues a run from its last completed frame: body and shell state, frame records and the
XDMF series (body and shell) are taken over, later output is dropped and recomputed.

Parallel runs: rank 0 builds or reads the mesh (gmsh and meshio are serial) and dolfinx
distributes it; an ``InputError`` on rank 0 is broadcast (:mod:`wrinkles.collective`) so every
rank raises the same error and no rank waits forever in a collective call.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import resource
import shlex
import shutil
import sys
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

import meshes
from meshes.errors import InputError, SolverError
from meshes.report import mesh_report
from meshes.tetmesh import TetMesh
from models.backend import MPI, dolfinx, mesh_from_arrays
from models.contact import mean_cell_size
from models.embedding.embedding import affine_maps
from models.rigid import RigidStepInfo
from solvers.body import Body, StepReport
from solvers.coupling import BallCoupling
from wrinkles.checkpoint import (
    CHECKPOINT_NAME,
    BodyState,
    gather_state,
    read_state,
    scatter_state,
    with_arrays,
    write_state,
)
from wrinkles.collective import on_root, shared
from wrinkles.output import (
    SUMMARY_NAME,
    WORK_DIR,
    XDMF_NAME,
    XdmfSeries,
    failure_diagnostic,
    json_text,
    one_line,
    short_diagnostic,
    summary_document,
    write_json_atomic,
)
from wrinkles.provenance import source_commit
from wrinkles.rigid_output import BALLS_XDMF_NAME, BallStep, ball_steps, write_balls
from wrinkles.scene import Scene, SceneMesh, mesh_builder, scene_dict
from wrinkles.set_up_checks import check_balls_outside, check_obstacles_clear, warn_pins
from wrinkles.shell_output import make_writer
from wrinkles.shell_setup import Shell, build_shell
from wrinkles.shell_stage import (
    check_resumed_target,
    one_way_stage,
    restore_shell,
    shell_arrays,
)
from wrinkles.two_way import two_way_stage

SUMMED: tuple[str, ...] = ("newton_iterations", "halvings", "substeps")
"""``StepReport`` counts that add up over the steps of a frame."""

RESTART_MAY_CHANGE: tuple[str, ...] = ("time", "output", "newton", "shell.solver")
"""Scene keys a ``--restart`` may change: time, output, the body's and the shell's solver
options (their threads change round-off only)."""

Stage = Callable[[int], Mapping[str, Any]]
"""One part of a frame: ``stage(frame)`` advances its model and returns record entries."""


@dataclass(frozen=True)
class FrameRecord:
    """What one frame did (one entry of ``summary.json``'s ``frames``).

    Attributes:
        frame: frame number, 1-based.
        time: physical time at the end of the frame [s].
        newton_iterations: body Newton iterations in this frame (all steps and halvings).
        energy: total body energy: kinetic + elastic + gravity + contact [J].
        min_det_f: minimum of det F over the body's quadrature points [-].
        wall_time: wall time of the frame, output included [s].
        cpu_time: CPU time of this process during the frame, all its threads [s].
        stage_times: wall time per stage [s] (in the overlapped layout the body stage's is
            the shell rank's wait for the body rank, :mod:`wrinkles.overlap`).
        details: further numbers returned by the stages (energy split, halvings, ...).

    """

    frame: int
    time: float
    newton_iterations: int
    energy: float
    min_det_f: float
    wall_time: float
    cpu_time: float = 0.0
    stage_times: dict[str, float] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)

    def progress_line(self, n_frames: int, static: bool = False) -> str:
        """Return the one-line progress report printed by rank 0.

        Static scenes show the load parameter instead of a time. Frames with a shell add its
        Newton iterations and solve time and, when the shell Newton stopped at its
        ``max_iterations`` above its gradient tolerance (the frame is kept, ``summary.json``
        says ``shell_converged: false``), ``NOT converged (|g| ... > ...)``, and when faces of
        the shell pass through each other, ``SELF-INTERSECTING (<pairs> face pairs)``
        (``shell_self_intersections``); two-way frames add
        ``coupling=<iterations>`` and, when the body/shell fixed point stopped at
        ``max_iterations`` above its tolerance, ``NOT converged (change ...)``.
        """
        clock = f"load={self.time:7.4f}" if static else f"t={self.time:9.4f} s"
        line = (f"frame {self.frame:4d}/{n_frames}  {clock}  "
                f"newton={self.newton_iterations:3d}  energy={self.energy: .6e} J  "
                f"min detF={self.min_det_f:.4f}")
        if "shell_iterations" in self.details:
            line += (f"  shell={self.details['shell_iterations']:3d} its "
                     f"{self.details.get('shell_time_total', 0.0):6.2f} s")
            if self.details.get("shell_converged") is False:
                line += (f" NOT converged (|g| {self.details['shell_grad_norm']:.1e} > "
                         f"{self.details['shell_tolerance']:.1e})")
            if self.details.get("shell_self_intersections", 0) > 0:
                line += (f" SELF-INTERSECTING ({self.details['shell_self_intersections']} face "
                         f"pairs)")
        line += f"  wall={self.wall_time:7.3f} s"
        if "coupling_iterations" in self.details:
            line += f"  coupling={self.details['coupling_iterations']}"
            if not self.details.get("coupling_converged", True):
                line += f" NOT converged (change {self.details['coupling_change']:.1e})"
        return line


# --------------------------------------------------------------------------------------------
# Mesh and body


def read_tet_mesh(spec: SceneMesh) -> TetMesh:
    """Build the coarse mesh with its gmsh builder, or read and validate its file (serial).

    What a user should know about the accepted mesh (pieces, cracks, slivers,
    :mod:`meshes.report`) is issued as a :class:`meshes.MeshWarning`.
    """
    tet = mesh_builder(spec.builder)(**spec.params) if spec.builder else meshes.load(spec.file)
    for message in mesh_report(tet).warnings(tet.source):
        warnings.warn(message, meshes.MeshWarning, stacklevel=2)
    return tet


def distributed_mesh(spec: SceneMesh, comm: MPI.Comm) -> dolfinx.mesh.Mesh:
    """Build the scene mesh on rank 0 and distribute it over ``comm`` as a dolfinx mesh."""
    tet = on_root(comm, lambda: read_tet_mesh(spec))
    if tet is None:
        return mesh_from_arrays(comm, np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64))
    return mesh_from_arrays(comm, tet.points, tet.tets)


def mesh_facts(mesh: dolfinx.mesh.Mesh, body: Body) -> dict[str, int]:
    """Global sizes of the mesh and the body's unknowns."""
    imap = mesh.topology.index_map
    return {"vertices": imap(0).size_global, "cells": imap(mesh.topology.dim).size_global,
            "dofs": body.V.dofmap.index_map.size_global * body.V.dofmap.index_map_bs}


def body_stage(body: Body, steps: int) -> Stage:
    """Make the stage that advances the body by ``steps`` steps of ``body.options.dt``."""

    def stage(frame: int) -> dict[str, Any]:
        reports = [body.step() for _ in range(steps)]
        return body_record(reports)

    return stage


def body_record(reports: list[StepReport]) -> dict[str, Any]:
    """Merge a frame's body step reports into record entries.

    Counts (Newton iterations, halvings, sub-steps) are summed, ``min det F`` is the minimum
    over the steps, everything else (time, energy and its split) is the last step's.
    """
    record = dataclasses.asdict(reports[-1])
    record.pop("converged", None)
    for name in SUMMED:
        record[name] = sum(getattr(r, name) for r in reports)
    record["min_det_f"] = min(r.min_det_f for r in reports)
    return record


# --------------------------------------------------------------------------------------------
# The run


@dataclass
class Run:
    """A scene being run: the body, its stages, the output directory and the records.

    Attributes:
        scene: the resolved scene.
        out: output directory.
        body: the coarse body.
        stages: ``(name, stage)`` pairs run in order every frame; the body stage first.
        series: the body's XDMF time series (``None`` when ``output.xdmf`` is off).
        records: one record per completed frame.
        facts: run facts for the summary (ranks, sizes, status, start time).
        shell: the embedded shell (``None`` without a ``[shell]`` table).
        rigid: the rigid balls and their coupling (``None`` without ``[[rigid.balls]]``).

    """

    scene: Scene
    out: Path
    body: Body
    stages: list[tuple[str, Stage]]
    series: XdmfSeries | None = None
    records: list[FrameRecord] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)
    shell: Shell | None = None
    rigid: BallCoupling | None = None
    started: float = field(default_factory=time.perf_counter)

    @property
    def comm(self) -> MPI.Comm:
        """The communicator of the body's mesh."""
        return self.body.mesh.comm

    @property
    def n_frames(self) -> int:
        """Frames this run will compute."""
        return self.scene.time.frames


def prepare(scene: Scene, out: Path, comm: MPI.Comm, restart: bool = False,
            overwrite: bool = False, log: Callable[[str], None] | None = None) -> Run:
    """Build mesh, body, balls and shell, then create the output and the stages (collective).

    Everything that can be refused (the output directory, the mesh, the shell set-up and its
    memory) is checked before the first file is written; an output directory created for a
    run whose set-up is refused is removed again. With ``restart`` the body state, the
    frame records and the XDMF series are taken over from the run in ``out`` (its last
    completed frame); otherwise a new run starts at t = 0, into a directory that holds no
    other run unless ``overwrite`` (then that run's files are removed first). ``log`` (rank 0)
    announces each set-up stage as it ends.
    """
    say = stage_logger(log if comm.rank == 0 else None)
    created = on_root(comm, lambda: check_output_dir(out, restart, overwrite))
    try:
        return _prepare(scene, out, comm, restart, overwrite, say)
    except BaseException:
        if created:  # rank 0 created it; removed only while it is still empty
            remove_if_empty(out)
        raise


def _prepare(scene: Scene, out: Path, comm: MPI.Comm, restart: bool, overwrite: bool,
             say: Callable[[str], None]) -> Run:
    """:func:`prepare` after the output directory was checked (collective)."""
    run = prepare_body(scene, out, comm, say)
    body = run.body
    shell = (None if scene.shell is None
             else build_shell(body, scene.shell, scene.material, log=say,
                              source=scene.mesh.file or f"mesh.builder {scene.mesh.builder}"))
    state: BodyState | None = None
    if restart:
        state = resume(run, None if shell is None
                       else lambda saved: restore_shell_state(shell, body, saved))
        if run.rigid is not None:
            run.rigid.restore(checkpoint_stage(state, "rigid"))
    else:
        if overwrite:
            on_root(comm, lambda: clear_run(out))
        start(run)
    if shell is not None:
        attach_shell(run, shell, state)
    if not restart:
        save_frame(run, 0)
    return run


def prepare_body(scene: Scene, out: Path, comm: MPI.Comm, say: Callable[[str], None]) -> Run:
    """Build the mesh, the body and its balls, with the body stage; no output (collective).

    The set-up :func:`prepare` shares with a rank that only steps the body
    (:mod:`wrinkles.overlap`). The scene's warnings about pins are issued on rank 0.
    """
    mesh = distributed_mesh(scene.mesh, comm)
    cells = mesh.topology.index_map(3).size_global
    say(f"mesh: {cells} tets on {comm.size} rank(s)")
    body = make_body(scene, mesh)
    say(f"body: P{scene.body.degree}, {body.V.dofmap.index_map.size_global * 3} dofs, forms "
        f"compiled" + (f"; pins hold {', '.join(map(str, body.pin_nodes))} nodes"
                       if body.pin_nodes else ""))
    nodes = body.V.tabulate_dof_coordinates()[: body.V.dofmap.index_map.size_local]
    warn_pins(scene, body.pin_nodes, nodes, comm, comm.rank == 0)
    stages: list[tuple[str, Stage]] = [("body", body_stage(body, scene.time.steps_per_frame))]
    run = Run(scene, out, body, stages)
    check_obstacles_clear(nodes, mean_cell_size(mesh), scene, comm, comm.rank == 0)
    if scene.rigid is not None and scene.rigid.balls:
        owned = np.arange(mesh.topology.index_map(3).size_local)
        check_balls_outside(affine_maps(mesh), owned, scene, comm)
        run.rigid = BallCoupling(body, scene.rigid.internals, len(scene.body.contacts))
        run.stages = [("body+rigid", rigid_stage(run.rigid, scene.time.steps_per_frame))]
    run.facts = {"ranks": comm.size, "layout": "split" if comm.size > 1 else "serial",
                 "status": "running", "frames_planned": run.n_frames,
                 "started": datetime.now(UTC).isoformat(timespec="seconds"),
                 "command": " ".join(shlex.quote(a) for a in sys.argv),
                 "commit": source_commit() if comm.rank == 0 else None,
                 "mesh": mesh_facts(mesh, body), "pin_nodes": body.pin_nodes}
    return run


def stage_logger(log: Callable[[str], None] | None) -> Callable[[str], None]:
    """Return ``say(text)``: ``log("set-up: <text> (<seconds> s)")`` timing from the last call."""
    last = [time.perf_counter()]

    def say(text: str) -> None:
        now = time.perf_counter()
        if log is not None:
            log(f"set-up: {text} ({now - last[0]:.2f} s)")
        last[0] = now

    return say


def make_body(scene: Scene, mesh: dolfinx.mesh.Mesh) -> Body:
    """Make the scene's body; the rigid balls' spheres follow the scene's own contacts."""
    options = scene.body
    if scene.rigid is not None and scene.rigid.balls:
        balls = tuple(ball.contact() for ball in scene.rigid.balls)
        options = dataclasses.replace(options, contacts=(*options.contacts, *balls))
    return Body(mesh, scene.material, options, scene.newton.internals)


def rigid_stage(coupling: BallCoupling, steps: int) -> Stage:
    """Make the stage that advances balls and body by ``steps`` coupled steps.

    A second call for the same frame (a two-way shell coupling redoing the frame's body steps
    from its snapshot) first puts the balls back to their state at the frame's start.
    """
    start: dict[str, Any] = {}

    def stage(frame: int) -> dict[str, Any]:
        if start.get("frame") == frame:
            coupling.restore(start["arrays"])
        else:
            start.update(frame=frame, arrays={k: np.array(v, copy=True)
                                              for k, v in coupling.arrays().items()})
        infos = [coupling.step() for _ in range(steps)]
        return {**body_record([i.report for i in infos]), **rigid_record(coupling, infos)}

    return stage


def rigid_record(coupling: BallCoupling, infos: list[RigidStepInfo]) -> dict[str, Any]:
    """Frame record entries of the balls: state, penetration, iterations, momentum balance."""
    state = coupling.state
    balls = [{"center": state.center[i].tolist(), "velocity": state.velocity[i].tolist(),
              "contact_force": state.force[i].tolist(),
              "penetration": max(info.penetration[i] for info in infos)}
             for i in range(len(state.center))]
    return {"balls": balls, "rigid_iterations": [info.iterations for info in infos],
            "rigid_mismatch": max(info.mismatch for info in infos),
            "momentum": coupling.balance()}


def restore_shell_state(shell: Shell, body: Body, state: BodyState) -> None:
    """Set the shell's state from a checkpoint and check it against the body's (collective).

    Raises:
        InputError: the checkpoint holds no shell state, or one of another shell
            (:func:`wrinkles.shell_stage.check_resumed_target`).

    """
    restore_shell(shell, checkpoint_stage(state, "shell"))
    check_resumed_target(shell, body)


def attach_shell(run: Run, shell: Shell, state: BodyState | None) -> None:
    """Create the shell's output and add its stage(s); its state was restored if resumed.

    Collective. ``state`` is the checkpoint of a resumed run (``None`` for a new run), whose
    shell state :func:`resume` restored (:func:`restore_shell_state`).
    """
    options = shell.options
    output, last = run.scene.output, run.n_frames
    write = (make_writer(shell, run.out, run.comm, lambda f: output.writes_frame(f, last),
                         None if state is None else state.time)
             if output.xdmf else (lambda frame, t: None))
    if options.coupling.mode == "two_way":
        body = run.stages[0][1]  # the body stage, or the body+rigid stage
        run.stages = [("body+shell", two_way_stage(shell, run.body, body, write))]
    else:
        run.stages.append(("shell", one_way_stage(shell, run.body, write)))
    run.shell = shell
    run.facts["shell"] = shell.facts


def checkpoint_stage(state: BodyState, stage: str) -> dict[str, np.ndarray]:
    """Return the arrays of ``stage`` in a checkpoint; InputError if it has none."""
    if stage not in state.arrays:
        raise InputError(f"{CHECKPOINT_NAME}: the checkpoint holds no {stage} state (written "
                         f"by a run without [{stage}] or by an older version); rerun from the "
                         "start")
    return state.arrays[stage]


def start(run: Run) -> None:
    """Write the mesh and the initial state (t = 0) of a new run's body series."""
    if run.scene.output.xdmf:
        run.series = XdmfSeries(run.out / XDMF_NAME, output_fields(run.body))
        run.series.write(run.body.t)


def resume(run: Run, restore: Callable[[BodyState], None] | None = None) -> BodyState:
    """Take over the state, records and output of the run in ``run.out`` (collective).

    ``restore`` (e.g. :func:`restore_shell_state`) takes the other stages' state once the
    body's is set and before anything in ``run.out`` is written, so that its refusal leaves
    the run on disk as it was.

    Returns:
        The checkpoint (its ``arrays`` hold the other stages' state, e.g. the shell's).

    Raises:
        InputError: no checkpoint or summary in ``run.out``, or its scene differs from this
            one in anything but ``time``, ``output`` and ``newton``; or ``restore``'s.

    """
    state = shared(run.comm, lambda: read_state(run.out / CHECKPOINT_NAME))
    records, facts = shared(run.comm, lambda: previous_run(run, state.frame))
    scatter_state(run.body, state)
    if restore is not None:
        restore(state)
    run.records = records
    run.facts["restarts"] = [*facts.get("restarts", []), {"frame": state.frame,
                                                          "time": state.time,
                                                          "ranks": run.comm.size}]
    if run.scene.output.xdmf:
        run.series = XdmfSeries(run.out / XDMF_NAME, output_fields(run.body),
                                resume_after=state.time)
    write_summary(run)
    return state


def previous_run(run: Run, frame: int) -> tuple[list[FrameRecord], dict[str, Any]]:
    """Read ``summary.json`` of the run being restarted: its first ``frame`` records and facts.

    Raises:
        InputError: the checkpoint holds more frames than the scene asks for, the summary is
            missing, or the scene changed (but time, output, newton).

    """
    path = run.out / SUMMARY_NAME
    if frame > run.n_frames:
        raise InputError(f"--resume: {run.out} already holds {frame} frames, more than the "
                         f"{run.n_frames} asked (ask for {frame} or more, or --overwrite to "
                         "start again)")
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the summary of the run to restart "
                         f"({exc})") from None
    changed = first_difference(summary.get("scene", {}), jsonable(scene_dict(run.scene)),
                               ignore=RESTART_MAY_CHANGE)
    if changed is not None:
        raise InputError(f"--restart: the scene differs from the run in {run.out} at "
                         f"'{changed}' (only {', '.join(RESTART_MAY_CHANGE)} may change)")
    try:
        records = [FrameRecord(**r) for r in summary.get("frames", [])[:frame]]
    except TypeError as exc:
        raise InputError(f"{path}: frame records of another format ({exc})") from None
    if len(records) != frame:
        raise InputError(f"{path}: has {len(records)} frame records, the checkpoint is at "
                         f"frame {frame}")
    return records, summary.get("run", {})


def jsonable(data: Any) -> Any:
    """Return ``data`` as it reads back from ``summary.json`` (tuples become lists, inf "inf")."""
    return json.loads(json_text(data))


def first_difference(old: Any, new: Any, prefix: str = "",
                     ignore: tuple[str, ...] = ()) -> str | None:
    """Return the first dotted key whose value differs between two JSON documents.

    ``ignore`` lists dotted keys (from the root) left out of the comparison.
    """
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            path = f"{prefix}.{key}".strip(".")
            if path in ignore:
                continue
            found = first_difference(old.get(key), new.get(key), path, ignore)
            if found is not None:
                return found
        return None
    return None if old == new else (prefix or "<root>")


def save_frame(run: Run, frame: int) -> None:
    """Write the summary, the balls' series and the checkpoint of a completed frame."""
    write_summary(run)
    if run.rigid is not None and run.scene.rigid is not None and run.comm.rank == 0:
        balls = run.scene.rigid.balls
        initial = BallStep(0.0, np.array([b.center for b in balls], dtype=float),
                           np.array([b.velocity for b in balls], dtype=float))
        write_balls(run.out / BALLS_XDMF_NAME, ball_steps(initial, run.records),
                    np.array([b.radius for b in balls]))
    state = gather_state(run.body, frame)
    if state is not None and run.shell is not None:
        state = with_arrays(state, "shell", shell_arrays(run.shell))
    if state is not None and run.rigid is not None:
        state = with_arrays(state, "rigid", run.rigid.arrays())
    if state is not None:
        write_state(run.out / CHECKPOINT_NAME, state)


RUN_MARKERS: tuple[str, ...] = (SUMMARY_NAME, CHECKPOINT_NAME, XDMF_NAME, "shell.xdmf")
"""Files that show a directory holds a run."""
RUN_FILES: tuple[str, ...] = (*RUN_MARKERS, "body.h5", "body.steps", "shell.h5", "shell.steps",
                              BALLS_XDMF_NAME, "shell.png", "shell.gif", "frames", "plots.png",
                              "view.py", "view.png", "vtk", WORK_DIR)
"""What a run writes into its output directory (``--overwrite`` removes these, nothing else)."""


def check_output_dir(out: Path, resume: bool, overwrite: bool) -> bool:
    """Refuse an output directory that holds another run; create ``out`` and probe writing.

    A new run never mixes its files with another's: ``out`` may not hold a run's files
    unless the run is resumed (``--resume``) or replaced (``--overwrite``).

    Returns:
        Whether ``out`` was created here (it did not exist before).

    Raises:
        InputError: ``out`` is a file, holds another run, cannot be created or written.

    """
    if resume and overwrite:
        raise InputError("--resume and --overwrite exclude each other")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file, not a directory")
    found = [name for name in RUN_MARKERS if (out / name).exists()]
    if found and not (resume or overwrite):
        raise InputError(f"--out {out}: holds another run ({', '.join(found)}); use --resume "
                         f"to continue it or --overwrite to replace it")
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise InputError(f"--out {out}: cannot write the output directory "
                         f"({exc.strerror or exc})") from None
    return created


def remove_if_empty(out: Path) -> None:
    """Remove the directory ``out`` if it holds nothing (a refused run leaves no trace)."""
    with contextlib.suppress(OSError):
        out.rmdir()


def clear_run(out: Path) -> None:
    """Remove the files of the run in ``out`` (:data:`RUN_FILES`; other files stay)."""
    for name in RUN_FILES:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def output_fields(body: Body) -> dict[str, Any]:
    """Return the body fields written to the XDMF file, by output name."""
    return {"displacement": body.u, "velocity": body.v}


def run_frame(run: Run, frame: int) -> FrameRecord:
    """Run every stage once, then write the frame's output (collective)."""
    start, cpu = time.perf_counter(), time.process_time()
    values: dict[str, Any] = {}
    stage_times: dict[str, float] = {}
    for name, stage in run.stages:
        t0 = time.perf_counter()
        values.update(stage(frame))
        stage_times[name] = time.perf_counter() - t0
    if run.series is not None and run.scene.output.writes_frame(frame, run.n_frames):
        run.series.write(run.body.t)
    return make_record(frame, values, stage_times, time.perf_counter() - start,
                       time.process_time() - cpu)


def make_record(frame: int, values: dict[str, Any], stage_times: dict[str, float],
                wall: float, cpu: float = 0.0) -> FrameRecord:
    """Split stage values into the record's main fields and its details."""
    main = {f.name for f in dataclasses.fields(FrameRecord)}
    details = {k: v for k, v in values.items() if k not in main}
    core = {k: v for k, v in values.items() if k in main}
    return FrameRecord(frame=frame, wall_time=wall, cpu_time=cpu, stage_times=stage_times,
                       details=details, **core)


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far [MiB] (``ru_maxrss``, KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def contact_facts(body: Body) -> dict[str, Any] | None:
    """Return the body's contact facet selection over the run (collective; None: no obstacle).

    ``share``: the facets the body solves integrated the penalties over, as a fraction of all
    exterior facets times obstacles (:mod:`solvers.contact_set`); ``retries``: solves repeated
    over all facets because a facet left out was penetrated. Counted over the frames this
    process ran (a resumed run from its resume on).
    """
    stats = body.contact_set
    if stats is None:
        return None
    kept, total = (body.mesh.comm.allreduce(v, op=MPI.SUM) for v in (stats.facets, stats.total))
    return {"solves": stats.solves, "share": kept / total if total else 0.0,
            "retries": stats.retries}


def write_summary(run: Run) -> None:
    """Rewrite ``summary.json`` atomically on rank 0."""
    if run.comm.rank == 0:
        frames = [dataclasses.asdict(r) for r in run.records]
        document = summary_document(scene_dict(run.scene), run.facts, frames)
        write_json_atomic(run.out / SUMMARY_NAME, document)


def report_done(run: Run, log: Callable[[str], None] = print) -> None:
    """Say so (rank 0) when a resumed run already holds every frame asked for."""
    if len(run.records) >= run.n_frames and run.comm.rank == 0:
        log(f"{run.out}: all {run.n_frames} frames are done already")


def run_frames(run: Run, log: Callable[[str], None] = print, render: bool = True) -> Run:
    """Run every frame of a prepared run; rank 0 passes one progress line per frame to ``log``.

    Then, with ``render`` and ``output.render``, its ranks render the shell
    (:func:`render_if_asked`).

    Raises:
        SolverError: a step failed after all halvings; ``summary.json`` records the failure
            and the frames completed before it stay on disk.
        InputError: an input only a solve can check (an expert PETSc option of the factor that
            its first set-up did not read), recorded the same way.

    """
    for frame in range(len(run.records) + 1, run.n_frames + 1):
        try:
            record = run_frame(run, frame)
        except (SolverError, InputError) as exc:
            run.facts.update(status="failed", error=str(exc), failed_frame=frame,
                             wall_time=time.perf_counter() - run.started)
            write_summary(run)
            raise
        run.records.append(record)
        save_frame(run, frame)
        if run.comm.rank == 0:
            log(record.progress_line(run.n_frames, run.scene.body.dynamics == "static"))
    run.facts["status"] = "completed"
    run.facts["wall_time"] = time.perf_counter() - run.started
    run.facts["peak_memory_mb"] = run.comm.allgather(peak_memory_mb())
    contact = contact_facts(run.body)
    if contact is not None:
        run.facts["contact_facets"] = contact
    run.facts["body_linear"] = run.body.linear_facts()
    write_summary(run)
    if run.comm.rank == 0:
        shutil.rmtree(run.out / WORK_DIR, ignore_errors=True)
    if render:
        render_if_asked(run, log)
    return run


def record_failure(run: Run, exc: SolverError) -> str:
    """Add the failure diagnostic to ``summary.json``; return the one-line stderr message.

    Collective. The message is the solver's, followed by the short form of the diagnostic
    (worst det F and its cell, dominant energy term, material and step parameters). An
    ``exc`` with a ``diagnostic`` attribute (a failure on another rank) brings its own.
    """
    diagnostic = getattr(exc, "diagnostic", None) or failure_diagnostic(run.body,
                                                                        one_line(str(exc)))
    run.facts["diagnostic"] = diagnostic
    write_summary(run)
    return f"{diagnostic['error']}; diagnostic: {short_diagnostic(diagnostic)}"


def render_if_asked(run: Run, log: Callable[[str], None], comm: MPI.Comm | None = None) -> None:
    """Render the shell series (PNG frames, ``shell.png``, ``shell.gif``) if the scene asks.

    Collective over ``comm`` (default the run's): its ranks share the frames
    (:func:`wrinkles.render.render_run`); rank 0 logs.
    """
    if run.scene.shell is None or not run.scene.output.render:
        return
    from wrinkles.render import RenderOptions, render_run

    comm = run.comm if comm is None else comm
    written = render_run(run.out, RenderOptions(), comm)
    if comm.rank == 0:
        log(f"rendered {len(written)} files into {run.out} (frames over {comm.size} rank(s))")


def run_scene(scene: Scene, out: Path, comm: MPI.Comm, log: Callable[[str], None] = print,
              restart: bool = False) -> Run:
    """Prepare ``scene`` (mesh, body, output in ``out``) and run its (remaining) frames."""
    return run_frames(prepare(scene, out, comm, restart), log)
