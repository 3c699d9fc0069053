"""Body and shell stages overlapped on two ranks: a one-way scene under ``mpiexec -n 2``.

In a one-way scene the shell follows the body (Algorithm 1 of the draft, Rémillard & Kry
2013): the body's frame ``k + 1`` does not depend on the shell's frame ``k``. Two ranks can
then overlap the stages instead of splitting each over both ranks: rank 1 steps the body (and
its rigid balls) frame after frame and sends each frame's end state to rank 0, which sets it
into its own copy of the body, runs the shell stage and writes all output, as a serial run
(:func:`wrinkles.runner.prepare` on ``COMM_SELF``); at the end both ranks render the shell's
frames (:func:`wrinkles.runner.render_if_asked`). A frame then costs about
``max(body, shell)`` instead of ``body_2 + shell_2``, the stages' times on two split ranks;
the frames equal the serial run's bit for bit. ``shell.solver.layout`` chooses
(:func:`choose_layout`); ``"auto"`` overlaps where the body is small (its stage does not
divide over ranks) and a large share of the frame (docs/notes/overlap-layout.md).

Messages (rank 1 -> 0, ``FRAME``): per frame the body stage's record entries, its wall time
and the body's state (:meth:`solvers.body.Body.snapshot`, the balls' arrays), or the step's
failure with its diagnostic, or ``end`` after a stop. Rank 0 -> 1 (``DONE``): after each
frame ``ok``, or ``stop`` with the error that ended the run. Rank 1 runs at most
:data:`LOOKAHEAD` frames ahead of rank 0. At the end rank 1 sends its peak memory and contact
facets (``FACTS``). Before the frames rank 0 sends the first frame and, for a resumed run,
the checkpoint's state (``START``).

Failures end both ranks with the same exit code: a body step failure reaches rank 0 after the
frames before it (which it completes and saves, as a serial run would); a failure on rank 0
stops rank 1 at its next frame. ``summary.json`` records the failure as a serial run does.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from meshes.errors import InputError, SolverError, WrinklesError
from meshes.tetmesh import TetMesh
from models.backend import MPI
from models.embedding.surface import boundary_surface
from wrinkles.collective import shared
from wrinkles.output import failure_diagnostic, one_line
from wrinkles.runner import (
    Run,
    contact_facts,
    peak_memory_mb,
    prepare,
    prepare_body,
    read_tet_mesh,
    record_failure,
    render_if_asked,
    report_done,
    run_frames,
    write_summary,
)
from wrinkles.scene import Scene
from wrinkles.shell_setup import shell_vertices

SHELL_RANK, BODY_RANK = 0, 1
START, FRAME, DONE, FACTS = 401, 402, 403, 404
"""Message tags of the overlapped layout."""
LOOKAHEAD = 2
"""Frames the body rank may run ahead of the shell rank."""
POLL_SECONDS = 2e-4
"""Sleep between probes of a rank waiting for the other (:func:`patient_recv`)."""
Failure = tuple[type[WrinklesError], str]
"""An error passed to the other rank: its class and message."""
MAX_BODY_DOFS = 2500
"""Bodies up to this many dofs overlap under ``"auto"``: their stage does not divide over two
ranks (the demo's 1 050 dofs); the full sofa's 4 386 and the bunny's 14 010 do and keep
the split (docs/notes/overlap-layout.md)."""
MIN_BODY_SHARE = 0.25
"""Smallest estimated body share of the frame (:attr:`Sizes.body_share`) that overlaps under
``"auto"``: below it the split's division of the shell gains more."""


@dataclass(frozen=True)
class Sizes:
    """What :func:`choose_layout` weighs: the body's and the shell's unknowns.

    Attributes:
        body_dofs: the body's displacement dofs (3 per P1 or P2 node).
        steps: body steps per frame.
        shell_vertices: vertices of the subdivided shell.

    """

    body_dofs: int
    steps: int
    shell_vertices: int

    @property
    def work(self) -> int:
        """A frame's work in shell-vertex solves: ``n_b s + V`` (see :attr:`body_share`)."""
        return self.body_dofs * self.steps + self.shell_vertices

    @property
    def body_share(self) -> float:
        """Estimated body share of a serial frame: ``n_b s / (n_b s + V)``.

        ``n_b`` body dofs times ``s`` steps against the shell's ``V`` vertices: one body dof
        step and one shell vertex solve cost about the same in the shipped scenes (the
        demo: 0.75 s for 21 000 dof steps, 1.65 s for 52 180 vertex solves).
        """
        return self.body_dofs * self.steps / self.work


def scene_sizes(scene: Scene) -> Sizes:
    """Read or build the scene's mesh (serial, its warnings silenced) and count the unknowns.

    A scene without a shell has no shell vertices.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tet = read_tet_mesh(scene.mesh)
    vertices = 0
    if scene.shell is not None:
        faces = boundary_surface(tet.points, tet.tets).faces.shape[0]
        vertices = shell_vertices(faces, scene.shell.subdivision.levels)
    return Sizes(body_dofs(tet, scene.body.degree), scene.time.steps_per_frame, vertices)


def body_dofs(tet: TetMesh, degree: int) -> int:
    """Displacement dofs of a P1 (vertices) or P2 (vertices and edges) body on ``tet``."""
    nodes = np.unique(tet.tets).size
    if degree == 2:
        edges = tet.tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
        nodes += np.unique(np.sort(edges, axis=1), axis=0).shape[0]
    return 3 * nodes


def choose_layout(scene: Scene, comm: MPI.Comm) -> str:
    """Return ``"overlap"`` or ``"split"`` for running ``scene`` on ``comm`` (collective).

    :func:`layout_for` with the sizes counted on rank 0 (only when ``"auto"`` needs them).
    """
    return layout_for(scene, comm.size, lambda: shared(comm, lambda: scene_sizes(scene)))


def layout_for(scene: Scene, ranks: int, sizes: Callable[[], Sizes]) -> str:
    """Return ``"overlap"`` or ``"split"`` for ``scene`` on ``ranks`` ranks.

    One rank runs serially (``"split"``). Else ``shell.solver.layout`` decides; ``"auto"``
    overlaps a one-way scene of two or more frames on two ranks whose body has at most
    :data:`MAX_BODY_DOFS` dofs and an estimated share of at least :data:`MIN_BODY_SHARE`
    (:class:`Sizes`; ``sizes()`` is called only then).

    Raises:
        InputError: ``"overlap"`` asked for a scene or rank count it does not apply to.

    """
    shell = scene.shell
    if shell is None or shell.solver.layout == "split" or ranks == 1:
        return "split"
    applies = ranks == 2 and shell.coupling.mode == "one_way"
    if shell.solver.layout == "overlap":
        if not applies:
            raise InputError(f"shell.solver.layout = \"overlap\": needs a one-way shell on "
                             f"two ranks (this run: {shell.coupling.mode} on {ranks} "
                             f"rank(s)); use \"auto\" or \"split\"")
        return "overlap"
    if not applies or scene.time.frames < 2:
        return "split"
    counted = sizes()
    overlaps = counted.body_dofs <= MAX_BODY_DOFS and counted.body_share >= MIN_BODY_SHARE
    return "overlap" if overlaps else "split"


class BodyRankFailure(SolverError):
    """A body step failed on the body rank; ``diagnostic`` is its failure record there."""

    def __init__(self, message: str, diagnostic: dict[str, Any]) -> None:
        """Keep the body rank's message and diagnostic."""
        super().__init__(message)
        self.diagnostic = diagnostic


def run_overlapped(scene: Scene, out: Path, comm: MPI.Comm, restart: bool = False,
                   overwrite: bool = False, log: Callable[[str], None] = print) -> Run | None:
    """Run ``scene`` with its stages overlapped on the two ranks of ``comm`` (collective).

    Returns:
        The run on rank 0 (output, records, summary), ``None`` on rank 1.

    Raises:
        InputError: the set-up failed on either rank (every rank raises).
        SolverError: a step failed on either rank (every rank raises; rank 0's message has
            the diagnostic, as :func:`wrinkles.runner.record_failure` writes it).

    """
    scene = single_thread(scene)
    if comm.rank == SHELL_RANK:
        log("layout: the body on rank 1, the shell and the output on rank 0, their stages "
            "overlapped (shell.solver.layout)")
        run = agreed(comm, lambda: prepare(scene, out, MPI.COMM_SELF, restart, overwrite, log))
        report_done(run, log)
        ShellSide(comm, run, restart).frames(log)
        return run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # rank 0 issues the scene's warnings
        body = agreed(comm, lambda: prepare_body(scene, out, MPI.COMM_SELF, lambda _: None))
    BodySide(comm, body).frames()
    return None


def single_thread(scene: Scene) -> Scene:
    """Return ``scene`` with an automatic shell thread count set to 1.

    The other rank's core steps the body; a second shell thread would share it.
    """
    if scene.shell is None or scene.shell.solver.threads != 0:
        return scene
    solver = dataclasses.replace(scene.shell.solver, threads=1)
    return dataclasses.replace(scene, shell=dataclasses.replace(scene.shell, solver=solver))


def agreed(comm: MPI.Comm, make: Callable[[], Run]) -> Run:
    """Run this rank's set-up; if any rank's failed, raise that error on every rank."""
    failure: Failure | None = None
    try:
        run = make()
    except WrinklesError as exc:
        failure = (type(exc), str(exc))
    arrived = comm.Ibarrier()  # the body's set-up ends first: wait without spinning
    while not arrived.Test():
        time.sleep(POLL_SECONDS)
    failures = comm.allgather(failure)
    first = next((f for f in failures if f is not None), None)
    if first is not None:
        mine = failures[comm.rank] or first
        raise mine[0](mine[1])
    return run


def patient_recv(comm: MPI.Comm, source: int, tag: int) -> Any:
    """Receive a pickled message, probing every :data:`POLL_SECONDS` until it is there.

    A blocking ``MPI_Recv`` spins its core while it waits; the rank that waits here (the body
    rank ahead of the shell, or the reverse) would take cycles from the other rank's stage
    wherever two ranks share a core's resources.
    """
    while not comm.Iprobe(source=source, tag=tag):
        time.sleep(POLL_SECONDS)
    return comm.recv(source=source, tag=tag)


class ShellSide:
    """Rank 0: receives the body's frames into its run and runs the shell stage and output."""

    def __init__(self, comm: MPI.Comm, run: Run, restart: bool) -> None:
        """Send the start state and put the receiving stage in place of the body stage."""
        self.comm, self.run = comm, run
        self.first = len(run.records) + 1
        self.sent: list[MPI.Request] = []
        state = None
        if restart:  # the body rank starts from the checkpoint's state, as a serial resume
            b = run.body
            state = {"t": b.t, "u": b.u.x.array, "v": b.v.x.array, "a": b.a.x.array,
                     "rate": b.rate.x.array,
                     "rigid": None if run.rigid is None else run.rigid.arrays()}
        comm.send({"first": self.first, "state": state}, dest=BODY_RANK, tag=START)
        name = run.stages[0][0]
        run.stages = [(name, self.receive), *run.stages[1:]]
        run.facts.update(ranks=comm.size, layout="overlap")
        write_summary(run)

    def receive(self, frame: int) -> dict[str, Any]:
        """Run rank 0's body stage: confirm the last frame, take this frame's body state."""
        if frame > self.first:
            self.done(frame - 1, "ok")
        message = patient_recv(self.comm, BODY_RANK, FRAME)
        run = self.run
        run.body.restore(message["state"])
        if run.rigid is not None:
            run.rigid.restore(message["rigid"])
        if "error" in message:
            raise BodyRankFailure(message["error"], message["diagnostic"])
        return {**message["values"], "body_rank_time": message["seconds"]}

    def done(self, frame: int, status: str, failure: Failure | None = None) -> None:
        """Tell the body rank that ``frame`` is complete (``ok``) or the run stopped.

        ``failure`` is the stopping error's class and message; the body rank raises it alike.
        """
        self.sent.append(self.comm.isend((frame, status, failure), dest=BODY_RANK, tag=DONE))

    def frames(self, log: Callable[[str], None]) -> None:
        """Run the frames; on a failure stop the body rank, record it and raise."""
        try:
            run_frames(self.run, log, render=False)
        except Exception as exc:
            kind = type(exc) if isinstance(exc, WrinklesError) else SolverError  # exit 2
            self.done(len(self.run.records) + 1, "stop", (kind, one_line(str(exc))))
            if not isinstance(exc, BodyRankFailure):
                self.drain()
            MPI.Request.Waitall(self.sent)
            if isinstance(exc, SolverError):
                raise SolverError(record_failure(self.run, exc)) from None
            raise
        if self.first <= self.run.n_frames:
            self.done(self.run.n_frames, "ok")
        facts = patient_recv(self.comm, BODY_RANK, FACTS)
        MPI.Request.Waitall(self.sent)
        run = self.run
        run.facts["peak_memory_mb"] = [*run.facts["peak_memory_mb"], facts["peak_memory_mb"]]
        if facts["contact_facets"] is not None:
            run.facts["contact_facets"] = facts["contact_facets"]
        run.facts["body_linear"] = facts["body_linear"]
        run.facts["body_rank"] = {"wall_time": facts["wall_time"], "cpu_time": facts["cpu"]}
        write_summary(run)
        render_if_asked(run, log, self.comm)

    def drain(self) -> None:
        """Receive the body rank's frames still in flight, up to its ``end`` or failure."""
        while True:
            message = patient_recv(self.comm, BODY_RANK, FRAME)
            if "end" in message or "error" in message:
                return


class BodySide:
    """Rank 1: steps the body frame after frame and sends each frame's state to rank 0."""

    def __init__(self, comm: MPI.Comm, run: Run) -> None:
        """Take the start frame (and a resumed run's state) from rank 0."""
        self.comm, self.run = comm, run
        start = comm.recv(source=SHELL_RANK, tag=START)
        self.first: int = start["first"]
        self.confirmed = self.first - 1
        self.sent: list[MPI.Request] = []
        self.failed = False
        if start["state"] is not None:
            s = start["state"]
            run.body.set_state(s["t"], s["u"], s["v"], s["a"], s["rate"])
            if run.rigid is not None:
                run.rigid.restore(s["rigid"])

    def frames(self) -> None:
        """Step every frame, at most :data:`LOOKAHEAD` ahead; then send the facts."""
        run, stage = self.run, self.run.stages[0][1]
        wall, cpu = time.perf_counter(), time.process_time()
        for frame in range(self.first, run.n_frames + 1):
            self.wait(frame - 1 - LOOKAHEAD)
            t0 = time.perf_counter()
            try:
                values = stage(frame)
            except SolverError as exc:
                diagnostic = failure_diagnostic(run.body, one_line(str(exc)))
                self.failed = True
                self.comm.send({**self.state(), "error": str(exc), "diagnostic": diagnostic},
                               dest=SHELL_RANK, tag=FRAME)
                self.wait(frame)  # rank 0 completes the frames before and stops
                raise
            self.sent.append(self.comm.isend(
                {**self.state(), "values": values, "seconds": time.perf_counter() - t0},
                dest=SHELL_RANK, tag=FRAME))
        self.wait(run.n_frames)
        MPI.Request.Waitall(self.sent)
        self.comm.send({"peak_memory_mb": peak_memory_mb(), "contact_facets":
                        contact_facts(run.body), "body_linear": run.body.linear_facts(),
                        "wall_time": time.perf_counter() - wall,
                        "cpu": time.process_time() - cpu}, dest=SHELL_RANK, tag=FACTS)
        render_if_asked(run, lambda _: None, self.comm)  # its share of the frames

    def state(self) -> dict[str, Any]:
        """Return the body's state (and the balls') at the end of the last step."""
        rigid = self.run.rigid
        return {"state": self.run.body.snapshot(),
                "rigid": None if rigid is None else rigid.arrays()}

    def wait(self, frame: int) -> None:
        """Wait until rank 0 has completed ``frame``; raise its error if it stopped."""
        while self.confirmed < frame:
            _, status, failure = patient_recv(self.comm, SHELL_RANK, DONE)
            if status == "stop":
                if not self.failed:  # rank 0 drains the frames in flight up to this
                    self.comm.send({"end": True}, dest=SHELL_RANK, tag=FRAME)
                MPI.Request.Waitall(self.sent)
                kind, message = failure
                raise kind(message)
            self.confirmed += 1
