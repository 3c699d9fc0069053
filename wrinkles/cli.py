"""Command-line interface of the ``wrinkles`` console script.

``wrinkles run SCENE.toml [--out DIR] [--frames N] [--set key=value ...] [--resume]`` runs a
scene (``--resume`` continues the run in ``DIR`` from its last completed frame; ``--restart``
is an alias kept for old scripts);
``wrinkles check SCENE.toml [--set key=value ...]`` validates it and prints it resolved (JSON).

Exit codes: 0 ok; 1 bad input (``InputError``: one line ``error: <message>`` on stderr, no
traceback; also bad command-line usage); 2 solver failure (``SolverError``: the frames done so
far and the checkpoint stay on disk, ``summary.json`` gets ``run.diagnostic`` - worst det F
cell, energy terms, parameters - which is also printed on stderr as one ``diagnostic:`` JSON
line) or an unexpected exception (a bug: its traceback is printed).

A ``wrinkles run`` started without ``mpiexec`` on a frame of
:data:`solvers.solver_choice.RANKS_FROM_WORK` shell vertices and body dof steps or more
(:data:`~solvers.solver_choice.RANKS_FROM_BODY_WORK` body dof steps without a shell),
threads left to the code, replaces itself by ``mpiexec -n N wrinkles run ...`` on the
machine's cores (:func:`command_ranks`, before the FE stack loads; one line says so; ``--set
shell.solver.threads=1`` or ``mpiexec -n 1`` keeps one process).
Under MPI every rank runs the same code, split over the ranks; a one-way scene on two ranks may
instead overlap its body and shell stages, one rank each (:mod:`wrinkles.overlap`, chosen by
``shell.solver.layout``). Errors raised on all ranks (scene validation, mesh
errors broadcast from rank 0, solver failures, which are collective) end the run with the
error's exit code after rank 0 prints the message. An error raised on some ranks only cannot
be agreed on while the others wait in a collective call: after ``AGREE_SECONDS`` without
agreement the failing rank prints its message and calls ``MPI_Abort`` with the exit code.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from meshes.errors import InputError, SolverError, WrinklesError
from wrinkles import plot, render, view
from wrinkles.launch import mpiexec_beside, relaunch_on_ranks, under_launcher
from wrinkles.output import one_line
from wrinkles.provenance import version_text

if TYPE_CHECKING:
    from wrinkles.overlap import Sizes
    from wrinkles.scene import Scene

AGREE_SECONDS = 10.0
"""How long a failing rank waits for the other ranks to fail too before ``MPI_Abort``."""
ABORT_GRACE_SECONDS: float = 0.5
"""Pause between the failing rank's flushed message and ``MPI_Abort``: the abort kills the job
at once, and a line still in mpiexec's forwarding is lost otherwise."""


class ArgumentParser(argparse.ArgumentParser):
    """``argparse`` parser whose usage errors raise ``InputError`` (exit 1, one line)."""

    def error(self, message: str) -> NoReturn:
        """Raise ``InputError`` instead of printing usage and exiting with status 2."""
        raise InputError(f"{message} (see '{self.prog} --help')")


def build_parser() -> ArgumentParser:
    """Return the ``wrinkles`` argument parser."""
    parser = ArgumentParser(prog="wrinkles", description="Embedded thin shells for wrinkle "
                            "simulation on FEniCSx: run a scene file.")
    parser.add_argument("--version", action="version", version=version_text())
    commands = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    run = add_scene_arguments(commands.add_parser("run", help="run a scene file (TOML)"))
    run.add_argument("--out", type=Path, default=None,
                     help="output directory (default: out/<scene name>)")
    run.add_argument("--frames", type=int, default=None, help="number of frames to run "
                     "(replaces time.frames)")
    run.add_argument("--resume", "--restart", dest="resume", action="store_true",
                     help="continue the run in --out from its last completed frame (same "
                     "scene; time, output, newton and shell.solver may "
                     "change); --restart is an alias")
    run.add_argument("--overwrite", action="store_true",
                     help="replace the run in --out (its files are removed once the scene, "
                     "mesh and shell are checked; other files stay)")
    add_scene_arguments(commands.add_parser(
        "check", help="validate a scene file and print the resolved scene as JSON"))
    render.add_parser(commands)
    plot.add_parser(commands)
    view.add_parser(commands)
    return parser


def add_scene_arguments(parser: ArgumentParser) -> ArgumentParser:
    """Add the scene file and the ``--set`` overrides to a sub-command; return it."""
    parser.add_argument("scene", type=Path, help="scene file, e.g. scenes/default.toml")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="override a scene key, value as a TOML "
                        "literal (repeatable), e.g. --set material.E=2e4; --set quality=preview "
                        "selects a preset (wrinkles/presets.py), explicit keys win over it")
    return parser


def command_run(args: argparse.Namespace) -> int:
    """Load the scene, apply ``--frames`` and ``--set``, run it (collective).

    A serial command decides its ranks (:func:`command_ranks`) before the FE stack loads;
    when it goes on to ranks, the scene's warnings are left to them (said once, not twice).
    """
    from wrinkles.overlap import choose_layout, run_overlapped
    from wrinkles.runner import prepare, record_failure, report_done, run_frames
    from wrinkles.scene import load_scene, with_frames

    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        scene = load_scene(args.scene, args.overrides)
        if args.frames is not None:
            scene = with_frames(scene, args.frames)
    if args.command_line is not None:
        ranks, why = command_ranks(scene)
        if ranks > 1:
            print(f"wrinkles: {why}: running on {ranks} MPI ranks (mpiexec -n {ranks}; "
                  f"{one_process(scene)} keeps one process)", flush=True)
            relaunch_on_ranks(ranks, args.command_line)
    for warning in said:
        warnings.warn_explicit(warning.message, warning.category, warning.filename,
                               warning.lineno)
    from models.backend import MPI

    comm = MPI.COMM_WORLD
    out = args.out if args.out is not None else Path("out") / args.scene.stem
    if choose_layout(scene, comm) == "overlap":
        with frame_progress(scene.time.frames, comm.size) as log:
            run_overlapped(scene, out, comm, args.resume, args.overwrite, log)
        return 0
    run = prepare(scene, out, comm, restart=args.resume, overwrite=args.overwrite,
                  log=lambda line: print(line, flush=True))
    report_done(run, lambda line: print(line, flush=True))
    try:
        with frame_progress(run.n_frames - len(run.records), comm.size) as log:
            run_frames(run, log=log)
    except SolverError as exc:
        if comm.size > 1 and not ranks_agree():  # the others wait in a solver's collective
            abort_alone(exc)
        raise SolverError(record_failure(run, exc)) from None
    return 0


def one_process(scene: Scene) -> str:
    """Return how a user keeps a serial run of ``scene`` in one process.

    The shell's threads key, else (a body alone has no solver key for it) a launcher of one
    rank.
    """
    return "mpiexec -n 1 wrinkles run ..." if scene.shell is None \
        else "--set shell.solver.threads=1"


def command_ranks(scene: Scene, sizes: Callable[[], Sizes] | None = None) -> tuple[int, str]:
    """Ranks a serial ``wrinkles run`` of ``scene`` runs on, and why (1: this process).

    More than one only for a process no MPI launcher started, with the wheel's ``mpiexec``
    beside the interpreter, and a frame whose work (shell vertices + body dofs x steps; a
    body-only scene's body alone) :func:`solvers.solver_choice.choose_ranks` gives ranks
    for; an ``"overlap"`` layout takes two. ``sizes`` counts the unknowns (default:
    :func:`wrinkles.overlap.scene_sizes`, a read of the mesh), called only when some size
    would give ranks.
    """
    from solvers.solver_choice import available_cores, choose_ranks
    from wrinkles.overlap import scene_sizes

    shell = scene.shell
    if under_launcher(os.environ) or mpiexec_beside() is None:
        return 1, ""
    cores = available_cores()
    threads = shell.solver.threads if shell is not None else 0
    if choose_ranks(threads, sys.maxsize, cores) == 1:  # no size would go
        return 1, ""
    size = (sizes or (lambda: scene_sizes(scene)))()
    ranks = choose_ranks(threads, size.work, cores, shell=shell is not None)
    if shell is not None and shell.solver.layout == "overlap":
        ranks = min(ranks, 2)
    body = f"{size.body_dofs} body dofs x {size.steps} step(s), {cores} cores"
    return ranks, body if shell is None else f"{size.shell_vertices} shell vertices + {body}"


@contextlib.contextmanager
def frame_progress(frames: int, ranks: int) -> Iterator[Callable[[str], None]]:
    """Yield the frame logger: a live bar with ETA on a terminal, plain lines otherwise.

    The bar (rich) is used for a serial run whose standard output is a terminal; the progress
    lines are printed above it as they come. Under MPI or into a file or pipe every line is
    printed as it is, flushed.
    """
    if ranks > 1 or not sys.stdout.isatty():
        yield lambda line: print(line, flush=True)
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (TextColumn("frames"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("ETA"), TimeRemainingColumn())
    with Progress(*columns) as progress:
        task = progress.add_task("frames", total=frames)

        def log(line: str) -> None:
            progress.console.print(line, highlight=False, markup=False)
            if line.startswith("frame "):
                progress.advance(task)

        yield log


def command_check(args: argparse.Namespace) -> int:
    """Validate the scene and its mesh; print the scene and the values the run will use (JSON).

    The mesh is built or read and validated, the set-up checks that need only the mesh run
    (pins, obstacles, balls: :func:`wrinkles.set_up_checks.check_mesh_set_up`), the shell's
    surface subdivided and its stiffnesses, cluster sizing and memory estimate computed (no
    dolfinx body, no solve).
    """
    from models.backend import MPI
    from models.embedding.caps import flip_caps
    from models.embedding.surface import boundary_surface
    from solvers.solver_choice import choose_joint_split
    from wrinkles.output import json_text
    from wrinkles.overlap import layout_for, scene_sizes
    from wrinkles.runner import read_tet_mesh
    from wrinkles.scene import load_scene, scene_dict
    from wrinkles.set_up_checks import check_mesh_set_up
    from wrinkles.shell_setup import shell_report

    scene = load_scene(args.scene, args.overrides)
    if MPI.COMM_WORLD.rank != 0:
        return 0
    mesh = read_tet_mesh(scene.mesh)
    resolved: dict[str, Any] = {"mesh": {"source": mesh.source, "points": int(mesh.n_points),
                                         "tets": int(mesh.n_tets),
                                         **check_mesh_set_up(scene, mesh)},
                                "newton": dataclasses.asdict(scene.newton.internals)}
    if scene.rigid is not None:
        resolved["rigid"] = dataclasses.asdict(scene.rigid.internals.coupling)
    sizes = functools.cache(lambda: scene_sizes(scene))  # one read of the mesh for all
    resolved["ranks_of_a_serial_run"] = command_ranks(scene, sizes)[0]
    if scene.shell is not None:
        caps = flip_caps(boundary_surface(mesh.points, mesh.tets))
        resolved["shell"] = shell_report(scene.shell, scene.material, caps.surface.vertices,
                                         caps.surface.faces,
                                         static=scene.body.dynamics == "static")
        resolved["shell"]["cap_flips"] = caps.flips
        resolved["shell"]["layout_on_2_ranks"] = layout_for(scene, 2, sizes)
        if scene.shell.monolithic_two_way:
            split = choose_joint_split(2, resolved["shell"]["vertices"],
                                       resolved["shell"]["solver"]["method"])
            resolved["shell"]["joint_system_on_2_ranks"] = "split" if split else "whole"
    print(json_text({"scene": scene_dict(scene), "resolved": resolved}), end="", flush=True)
    return 0


COMMANDS = {"run": command_run, "check": command_check, "render": render.command_render,
            "plot": plot.command_plot, "view": view.command_view}
"""Sub-command name -> its function (``args -> exit code``)."""


def report(exc: BaseException) -> int:
    """Print the error as the exit-code contract says; return the exit code."""
    if isinstance(exc, WrinklesError):
        print(f"error: {one_line(str(exc))}", file=sys.stderr, flush=True)
        return exc.exit_code
    traceback.print_exception(exc, file=sys.stderr)
    print(f"error: unexpected {type(exc).__name__} (a bug, please report it with the "
          "traceback above)", file=sys.stderr, flush=True)
    return 2


def fail_collectively(exc: BaseException) -> int:
    """Agree with the other ranks on the failure, or abort them all; return the exit code.

    All ranks failing (the usual case: errors are collective) meet in a non-blocking barrier
    on a private communicator; rank 0 reports and everyone returns. If the others do not
    arrive within ``AGREE_SECONDS`` they are stuck elsewhere: report here and ``Abort``.
    """
    from models.backend import MPI

    comm = MPI.COMM_WORLD
    if comm.size == 1:
        return report(exc)
    if not ranks_agree():
        abort_alone(exc)
    if comm.rank == 0:
        report(exc)
    return exc.exit_code if isinstance(exc, WrinklesError) else 2


def ranks_agree() -> bool:
    """Whether every rank reaches this call within ``AGREE_SECONDS`` (a failing rank asks).

    A non-blocking barrier on :func:`agreement_comm`: ranks that failed together all call
    it; a rank that failed alone finds the others stuck in a solver's collective.
    """
    request = agreement_comm().Ibarrier()
    deadline = time.monotonic() + AGREE_SECONDS
    while not request.Test():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def abort_alone(exc: BaseException) -> NoReturn:
    """Report ``exc`` prefixed with this rank and ``MPI_Abort`` the job with its exit code."""
    from models.backend import MPI

    comm = MPI.COMM_WORLD
    print(f"[rank {comm.rank}] ", end="", file=sys.stderr)
    code = report(exc)
    sys.stderr.flush()
    time.sleep(ABORT_GRACE_SECONDS)  # let mpiexec forward the line before the kill
    comm.Abort(code)
    raise SystemExit(code)  # not reached: Abort ends the process


@functools.cache
def agreement_comm() -> Any:
    """Duplicate of COMM_WORLD used only to agree on failures (never mixed with solver traffic).

    Creating it is collective: :func:`main` calls this on every rank of a launched job before
    any work (a process no launcher started is alone: it never needs one).
    """
    from models.backend import MPI

    return MPI.COMM_WORLD.Dup()


def warning_line(message: Warning | str, category: type[Warning], *_: Any, **__: Any) -> str:
    """Format a warning as one ``warning: <message>`` line (no source line, no file)."""
    return f"warning: {one_line(str(message))}\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``wrinkles`` console script; return the exit code.

    Without ``argv`` (the console script, ``python -m wrinkles``) the command line is
    ``sys.argv``, and a serial ``run`` may go on to the machine's cores as MPI ranks
    (:func:`command_ranks`); with ``argv`` (a caller in Python) it stays in this process.
    """
    warnings.formatwarning = warning_line
    try:
        args = build_parser().parse_args(argv)
    except InputError as exc:
        return report(exc)
    args.command_line = sys.argv[1:] if argv is None else None
    try:
        if under_launcher(os.environ):  # a process of its own needs no agreement
            agreement_comm()
        return COMMANDS[args.command](args)
    except Exception as exc:  # noqa: BLE001  (mapped to exit codes, see module doc)
        return fail_collectively(exc)


def entry() -> NoReturn:
    """Run :func:`main` and exit with its code (``python -m wrinkles``)."""
    sys.exit(main())


if __name__ == "__main__":
    entry()
